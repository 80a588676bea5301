"""One COLMAP step through pycolmap 4.x (FeatureExtractionOptions, IncrementalPipelineOptions),
run by the profuse-sfm crate as `python3 -I -c <this file> STEP ARGUMENTS_JSON`.

Prints `PROFUSE_SFM_PROGRESS <done> <total>` lines for progress the crate can show; any
exception ends the process with a traceback on standard error and a non-zero status.
"""
import json
import sys

import pycolmap


def image_names(path):
    with open(path, encoding="utf-8") as f:
        return [line for line in f.read().splitlines() if line]


def extract(a, device, threads):
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = a["camera_model"]
    if a.get("camera_params"):
        reader.camera_params = a["camera_params"]
    options = pycolmap.FeatureExtractionOptions()
    options.use_gpu = False
    options.num_threads = threads
    if a.get("max_image_size"):
        options.max_image_size = a["max_image_size"]
    if a.get("max_num_features"):
        options.sift.max_num_features = a["max_num_features"]
    mode = pycolmap.CameraMode.SINGLE if a["single_camera"] else pycolmap.CameraMode.AUTO
    pycolmap.extract_features(
        a["database"],
        a["images"],
        image_names=image_names(a["image_list"]),
        camera_mode=mode,
        reader_options=reader,
        extraction_options=options,
        device=device,
    )


def match(a, device, threads):
    options = pycolmap.FeatureMatchingOptions()
    options.use_gpu = False
    options.num_threads = threads
    verification = pycolmap.TwoViewGeometryOptions()
    if a.get("seed") is not None:
        verification.ransac.random_seed = a["seed"]
    if a["matcher"] == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = a["overlap"]
        pycolmap.match_sequential(
            a["database"],
            matching_options=options,
            pairing_options=pairing,
            verification_options=verification,
            device=device,
        )
    else:
        pycolmap.match_exhaustive(
            a["database"],
            matching_options=options,
            verification_options=verification,
            device=device,
        )


def map_(a, threads):
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    if a.get("seed") is not None:
        options.random_seed = a["seed"]
    total = a["total"]
    registered = [0]

    def initial_pair():
        registered[0] = 2
        print(f"PROFUSE_SFM_PROGRESS {registered[0]} {total}", flush=True)

    def next_image():
        registered[0] += 1
        print(f"PROFUSE_SFM_PROGRESS {registered[0]} {total}", flush=True)

    models = pycolmap.incremental_mapping(
        a["database"],
        a["images"],
        a["output"],
        options=options,
        initial_image_pair_callback=initial_pair,
        next_image_callback=next_image,
    )
    # incremental_mapping writes OUTPUT/<index> itself; write again only what is missing.
    import os

    for index, model in models.items():
        path = os.path.join(a["output"], str(index))
        if not os.path.isfile(os.path.join(path, "images.bin")):
            os.makedirs(path, exist_ok=True)
            model.write(path)


def main():
    step, a = sys.argv[1], json.loads(sys.argv[2])
    threads = a.get("threads") or -1
    if a.get("seed") is not None and hasattr(pycolmap, "set_random_seed"):
        pycolmap.set_random_seed(a["seed"])
    device = pycolmap.Device.cpu
    if step == "extract":
        extract(a, device, threads)
    elif step == "match":
        match(a, device, threads)
    elif step == "map":
        map_(a, threads)
    else:
        sys.exit(f"unknown step {step!r}")


main()
