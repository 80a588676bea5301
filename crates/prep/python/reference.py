"""Independent numpy + onnxruntime reference for crates/prep's agreement tests.

    reference.py sam ENCODER DECODER RGB.bin W H OUT_H OUT_W PROMPT [PROMPT ...] OUTDIR
        SAM preprocessing (numpy bilinear, half-pixel centres, longest side 1024, pad,
        mean/std), the encoder, and one decoder call per prompt (X,Y: a click;
        X,Y,X0,Y0,X1,Y1: a click with a box). Writes
        input.f32, embedding.f32, masks_<k>.f32, iou.f32 into OUTDIR.
    reference.py pool EMBEDDING.f32 W H LABELS.u16 GH GW MASKS OUT.f32
        The mask descriptors: mask-pixel-count-weighted mean of the 64x64x256 embedding
        over each mask, L2-normalised.
    reference.py nan-encoder OUT.onnx
        A broken SAM-encoder stand-in: input [1,3,1024,1024] -> a [1,256,64,64] output of NaN.
    reference.py tiny-clip OUTDIR
        Tiny ONNX models with the interface of the Hugging Face CLIP exports
        (pixel_values [N,3,224,224] -> image_embeds [N,8]; input_ids, attention_mask
        [N,77] int64 -> text_embeds [N,8]) and their outputs on given inputs.
"""
import os
import sys

import numpy as np


def resize_bilinear(img, new_w, new_h):
    """Half-pixel-centre bilinear resize of an HxWxC float array (no antialiasing)."""
    h, w, _ = img.shape

    def axis(src, dst):
        s = np.maximum((np.arange(dst) + 0.5) * (src / dst) - 0.5, 0.0)
        i0 = np.minimum(np.floor(s).astype(np.int64), src - 1)
        i1 = np.minimum(i0 + 1, src - 1)
        return i0, i1, (s - i0)

    x0, x1, fx = axis(w, new_w)
    y0, y1, fy = axis(h, new_h)
    top = img[y0][:, x0] * (1 - fx)[None, :, None] + img[y0][:, x1] * fx[None, :, None]
    bot = img[y1][:, x0] * (1 - fx)[None, :, None] + img[y1][:, x1] * fx[None, :, None]
    return top * (1 - fy)[:, None, None] + bot * fy[:, None, None]


def sam_input(rgb):
    h, w, _ = rgb.shape
    scale = 1024.0 / max(w, h)
    nw, nh = int(w * scale + 0.5), int(h * scale + 0.5)
    x = resize_bilinear(rgb.astype(np.float64), nw, nh)
    x = (x - np.array([123.675, 116.28, 103.53])) / np.array([58.395, 57.12, 57.375])
    out = np.zeros((1024, 1024, 3))
    out[:nh, :nw] = x
    return out.transpose(2, 0, 1)[None].astype(np.float32), nw, nh


def sam(args):
    import onnxruntime as ort

    enc, dec, rgb_path, w, h, oh, ow = args[:7]
    points, outdir = args[7:-1], args[-1]
    w, h, oh, ow = int(w), int(h), int(oh), int(ow)
    rgb = np.fromfile(rgb_path, np.uint8).reshape(h, w, 3)
    x, nw, nh = sam_input(rgb)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    e = ort.InferenceSession(enc, opts)
    emb = e.run(None, {e.get_inputs()[0].name: x})[0]
    x.tofile(os.path.join(outdir, "input.f32"))
    emb.astype(np.float32).tofile(os.path.join(outdir, "embedding.f32"))
    d = ort.InferenceSession(dec, opts)
    ious = []
    for k, p in enumerate(points):
        v = [float(t) for t in p.split(",")]
        sx, sy = nw / w, nh / h
        if len(v) == 2:
            coords = np.array([[[v[0] * sx, v[1] * sy], [0.0, 0.0]]], np.float32)
            labels = np.array([[1, -1]], np.float32)
        else:  # a click with a box: corners labelled 2 and 3, no padding point
            coords = np.array([[[v[0] * sx, v[1] * sy], [v[2] * sx, v[3] * sy],
                                [v[4] * sx, v[5] * sy]]], np.float32)
            labels = np.array([[1, 2, 3]], np.float32)
        masks, iou, _ = d.run(None, {
            "image_embeddings": emb,
            "point_coords": coords,
            "point_labels": labels,
            "mask_input": np.zeros((1, 1, 256, 256), np.float32),
            "has_mask_input": np.zeros(1, np.float32),
            "orig_im_size": np.array([oh, ow], np.float32),
        })
        masks.astype(np.float32).tofile(os.path.join(outdir, f"masks_{k}.f32"))
        ious.append(float(iou.ravel()[0]))
    np.array(ious, np.float32).tofile(os.path.join(outdir, "iou.f32"))


def pool(args):
    emb_path, w, h, lab_path, gh, gw, masks, out = args
    w, h, gh, gw, masks = int(w), int(h), int(gh), int(gw), int(masks)
    emb = np.fromfile(emb_path, np.float32).reshape(256, 64, 64).astype(np.float64)
    labels = np.fromfile(lab_path, np.uint16).reshape(gh, gw)
    scale = 1024.0 / max(w, h)
    nw, nh = int(w * scale + 0.5), int(h * scale + 0.5)
    cx = np.minimum(np.floor((np.arange(gw) + 0.5) * nw / gw / 16).astype(int), 63)
    cy = np.minimum(np.floor((np.arange(gh) + 0.5) * nh / gh / 16).astype(int), 63)
    rows = []
    for m in range(masks):
        ys, xs = np.nonzero(labels == m)
        v = emb[:, cy[ys], cx[xs]].sum(axis=1)
        rows.append(v / np.linalg.norm(v))
    np.array(rows, np.float32).tofile(out)


def tiny_clip(args):
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    outdir = args[0]
    rng = np.random.default_rng(7)
    # Image: global average pool over the 224x224 plane, then a 3x8 projection.
    wi = rng.standard_normal((3, 8)).astype(np.float32)
    g = helper.make_graph(
        [helper.make_node("GlobalAveragePool", ["pixel_values"], ["p"]),
         helper.make_node("Flatten", ["p"], ["f"]),
         helper.make_node("MatMul", ["f", "W"], ["image_embeds"])],
        "tiny_clip_image",
        [helper.make_tensor_value_info("pixel_values", TensorProto.FLOAT, ["N", 3, 224, 224])],
        [helper.make_tensor_value_info("image_embeds", TensorProto.FLOAT, ["N", 8])],
        [numpy_helper.from_array(wi, "W")])
    onnx.save(helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]),
              os.path.join(outdir, "clip_image.onnx"))
    # Text: embedding table lookup of the ids, masked mean over the attention mask.
    table = rng.standard_normal((49408, 8)).astype(np.float32)
    g = helper.make_graph(
        [helper.make_node("Gather", ["T", "input_ids"], ["e"]),
         helper.make_node("Cast", ["attention_mask"], ["mf"], to=TensorProto.FLOAT),
         helper.make_node("Unsqueeze", ["mf", "ax"], ["m3"]),
         helper.make_node("Mul", ["e", "m3"], ["em"]),
         helper.make_node("ReduceSum", ["em", "ax1"], ["text_embeds"], keepdims=0)],
        "tiny_clip_text",
        [helper.make_tensor_value_info("input_ids", TensorProto.INT64, ["N", 77]),
         helper.make_tensor_value_info("attention_mask", TensorProto.INT64, ["N", 77])],
        [helper.make_tensor_value_info("text_embeds", TensorProto.FLOAT, ["N", 8])],
        [numpy_helper.from_array(table, "T"),
         numpy_helper.from_array(np.array([2], np.int64), "ax"),
         numpy_helper.from_array(np.array([1], np.int64), "ax1")])
    onnx.save(helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]),
              os.path.join(outdir, "clip_text.onnx"))
    # Reference outputs: the image model on the input file the test wrote, the text
    # model on the token ids the test wrote (OpenAI CLIP ids, zero padded).
    s = ort.InferenceSession(os.path.join(outdir, "clip_image.onnx"))
    if os.path.exists(os.path.join(outdir, "image_in.f32")):
        x = np.fromfile(os.path.join(outdir, "image_in.f32"), np.float32).reshape(-1, 3, 224, 224)
        y = s.run(None, {"pixel_values": x})[0]
        (y / np.linalg.norm(y, axis=1, keepdims=True)).astype(np.float32).tofile(
            os.path.join(outdir, "image_out.f32"))
    t = ort.InferenceSession(os.path.join(outdir, "clip_text.onnx"))
    if os.path.exists(os.path.join(outdir, "ids.i64")):
        ids = np.fromfile(os.path.join(outdir, "ids.i64"), np.int64).reshape(-1, 77)
        y = t.run(None, {"input_ids": ids, "attention_mask": (ids != 0).astype(np.int64)})[0]
        (y / np.linalg.norm(y, axis=1, keepdims=True)).astype(np.float32).tofile(
            os.path.join(outdir, "text_out.f32"))


def nan_encoder(args):
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    shape = numpy_helper.from_array(np.array([1, 256, 64, 64], np.int64), "shape")
    g = helper.make_graph(
        [helper.make_node("ConstantOfShape", ["shape"], ["embedding"],
                          value=helper.make_tensor("v", TensorProto.FLOAT, [1], [float("nan")]))],
        "nan_encoder",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, 1024, 1024])],
        [helper.make_tensor_value_info("embedding", TensorProto.FLOAT, [1, 256, 64, 64])],
        [shape])
    onnx.save(helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]), args[0])


if __name__ == "__main__":
    {"sam": sam, "pool": pool, "tiny-clip": tiny_clip, "nan-encoder": nan_encoder}[sys.argv[1]](
        sys.argv[2:])
