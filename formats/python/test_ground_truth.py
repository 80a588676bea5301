"""Tests of the ground-truth readers of ``profuse_formats`` (SPEC.md section 6.1): every
golden vector under ``formats/vectors/gt`` (written by the Rust side) gets the verdict,
error code and field listed in its ``expected.json``, and valid files read back their
values. Run: ``python3 formats/python/test_ground_truth.py``."""

from __future__ import annotations

import json
import pathlib
import sys
import tempfile
import unittest

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import profuse_formats as pf  # noqa: E402

GT = HERE.parent / "vectors" / "gt"


def read(path: pathlib.Path):
    if path.name.startswith("scene"):
        return pf.read_scene_truth(path)
    return pf.read_mask_objects(path)


class GoldenVectors(unittest.TestCase):
    def test_every_vector_gets_its_verdict(self) -> None:
        expected = json.loads((GT / "expected.json").read_text(encoding="utf-8"))
        self.assertGreaterEqual(len(expected), 6)
        for name, want in expected.items():
            path = GT.parent / name
            with self.subTest(name=name):
                if want["valid"]:
                    read(path)
                else:
                    with self.assertRaises(pf.GtError) as ctx:
                        read(path)
                    self.assertEqual((ctx.exception.code, ctx.exception.field),
                                     (want["code"], want["field"]))

    def test_valid_values(self) -> None:
        scene = pf.read_scene_truth(GT / "valid" / "scene.json")
        self.assertEqual(scene.object_classes(), [2, 5, 7])
        self.assertEqual(scene.room_size, (6.0, 5.0, 2.8))
        self.assertEqual(scene.objects[1].name, "chair_1")
        masks = pf.read_mask_objects(GT / "valid" / "mask_objects.json")
        self.assertEqual(masks.objects, [2, None, 1])


class Rules(unittest.TestCase):
    def edit(self, reader, text: str):
        with tempfile.TemporaryDirectory() as d:
            p = pathlib.Path(d) / "f.json"
            p.write_text(text, encoding="utf-8")
            with self.assertRaises(pf.GtError) as ctx:
                reader(p)
        return ctx.exception.code, ctx.exception.field

    def test_scene_rules(self) -> None:
        good = (GT / "valid" / "scene.json").read_text(encoding="utf-8")
        cases = [
            ("synth.scene", "other", "format"),
            ("6.0", "-6.0", "room.size"),
            ('"index": 1', '"index": 2', "objects[1].index"),
            ('"chair_1"', '"floor"', "objects[1].name"),
            ('"class_name": "chair"', '"class_name": "sofa"', "objects[1].class_name"),
        ]
        for old, new, field in cases:
            with self.subTest(field=field):
                self.assertIn(old, good)
                self.assertEqual(self.edit(pf.read_scene_truth, good.replace(old, new, 1)),
                                 ("invalid", field))
        self.assertEqual(self.edit(pf.read_scene_truth, "not json"), ("json", None))

    def test_mask_object_rules(self) -> None:
        r = pf.read_mask_objects
        self.assertEqual(self.edit(r, '{"num_masks": 2, "masks": [{"id": 0, "object": 1}]}'),
                         ("invalid", "masks"))
        self.assertEqual(
            self.edit(r, '{"num_masks": 1, "masks": [{"id": 0, "object": 4294967295}]}'),
            ("invalid", "masks[0].object"))
        self.assertEqual(self.edit(r, '{"num_masks": 1, "masks": [{"id": "0"}]}'),
                         ("json", None))
        self.assertEqual(self.edit(r, "{}"), ("json", None))

    def test_missing_file_is_io(self) -> None:
        with self.assertRaises(pf.GtError) as ctx:
            pf.read_mask_objects(GT / "absent.json")
        self.assertEqual(ctx.exception.code, "io")


if __name__ == "__main__":
    unittest.main()
