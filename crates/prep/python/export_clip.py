"""Export an open_clip model's image and text encoders to the ONNX interface `prep` reads.

    python export_clip.py --model ViT-B-32 --pretrained laion2b_s34b_b79k --out DIR
    python export_clip.py --model ViT-B-16 --pretrained /path/to/finetuned.pt --out DIR
    python export_clip.py --model ViT-S-32-alt --pretrained none --out DIR   # random weights

writes

    DIR/clip_image.onnx   pixel_values f32 [N,3,224,224] -> image_embeds f32 [N,D]
    DIR/clip_text.onnx    input_ids i64 [N,77]           -> text_embeds f32 [N,D]
    DIR/clip_export.json  what was exported (model, weights, D, normalisation, tokenizer,
                          the ONNX-vs-torch check when onnxruntime is installed)

for `prep features --clip-image DIR/clip_image.onnx`, `prep prompts --clip-text
DIR/clip_text.onnx` and `profuse prepare --clip-image ... --clip-text ...`.

What `prep` feeds the encoders, and how the export agrees with it (crates/prep/src/clip.rs):

* image: each mask's crop padded to a square, resized bilinearly to 224 x 224, scaled to 0..1
  and normalised with OpenAI CLIP's mean/std. A model trained with other constants (e.g.
  SigLIP-style 0.5/0.5, or --image-mean/--image-std) gets the per-channel affine map from
  prep's normalisation to its own baked into the graph (`renormalised` in the json). A model
  whose input side is not 224 is refused: prep crops at 224.
* text: OpenAI's CLIP BPE (instant-clip-tokenizer in Rust: start-of-text, the lower-cased
  tokens truncated to 75, end-of-text, zero padding to 77). The model's open_clip tokenizer
  must be that one (SimpleTokenizer, context 77, vocabulary 49408, the known ids of a probe
  sentence) and its text tower must pool at the end-of-text token; otherwise the export is
  refused. open_clip text towers use a causal mask, so padding never reaches the embedding
  and the text model takes no attention_mask (prep sends one only to models that have it).

The outputs are the projections before L2 normalisation (prep normalises them).

`--reference DIR` (used by crates/prep's test) also writes torch's own outputs of the same
model, L2-normalised, on inputs the caller put in DIR:
    DIR/image_in.f32  [N,3,224,224] f32, normalised as prep normalises (OpenAI constants)
                      -> DIR/torch_image.f32: encode_image on the same pixels normalised with
                      the model's own mean/std (no ONNX involved)
    DIR/texts.txt     one text a line
                      -> DIR/torch_ids.i64 (open_clip's tokenizer), DIR/torch_text.f32
                      (encode_text on those ids)

Needs: pip install open_clip_torch torch onnx (onnxruntime optional: the self-check).
"""
import argparse
import json
import os
import sys

# OpenAI CLIP's normalisation, the one prep applies (clip.rs CLIP_MEAN / CLIP_STD).
PREP_MEAN = (0.48145466, 0.4578275, 0.40821073)
PREP_STD = (0.26862954, 0.26130258, 0.27577711)
PREP_IMAGE_SIZE = 224
PREP_CONTEXT = 77
CLIP_VOCAB = 49408
SOT, EOT = 49406, 49407
# clip.tokenize("a photo of a cat") (the ids crates/prep's tokenizer test pins).
PROBE = ("a photo of a cat", [49406, 320, 1125, 539, 320, 2368, 49407])
INSTALL = "pip install open_clip_torch torch onnx"


class ExportError(Exception):
    """A refusal with a one-line reason (printed without a traceback)."""


def fail(message, code=1):
    print(f"export_clip.py: error: {message}", file=sys.stderr)
    sys.exit(code)


def import_modules():
    missing = []
    mods = {}
    for name in ("torch", "open_clip", "onnx"):
        try:
            mods[name] = __import__(name)
        except ImportError:
            missing.append({"open_clip": "open_clip_torch"}.get(name, name))
    if missing:
        fail(f"{', '.join(missing)} not installed in {sys.executable}: {INSTALL}", 2)
    return mods["torch"], mods["open_clip"]


def floats3(text, what):
    try:
        v = tuple(float(t) for t in text.split(","))
    except ValueError:
        v = ()
    if len(v) != 3 or any(not (x == x) for x in v):
        raise ExportError(f"{what} '{text}': expected three numbers a,b,c")
    return v


def side(size):
    return tuple(size) if isinstance(size, (tuple, list)) else (size, size)


def check_tokenizer(open_clip, name):
    """The model's tokenizer must be the one prep's Rust tokenizer reproduces."""
    from open_clip.tokenizer import SimpleTokenizer

    tok = open_clip.get_tokenizer(name)
    kind = type(tok).__name__
    if not isinstance(tok, SimpleTokenizer):
        raise ExportError(
            f"model {name} uses the {kind} tokenizer; prep tokenises with OpenAI's CLIP BPE "
            "(SimpleTokenizer), so its text ids would mean nothing to this model")
    ctx = getattr(tok, "context_length", None)
    vocab = getattr(tok, "vocab_size", None)
    if ctx != PREP_CONTEXT:
        raise ExportError(f"model {name} has text context {ctx}; prep sends {PREP_CONTEXT} tokens")
    if vocab != CLIP_VOCAB:
        raise ExportError(f"model {name} has vocabulary {vocab}; OpenAI's CLIP BPE has {CLIP_VOCAB}")
    clean = getattr(getattr(tok, "clean_fn", None), "__name__", "")
    if clean not in ("", "_clean_lower"):
        raise ExportError(
            f"model {name}'s tokenizer cleans text with {clean}; prep's only lower-cases")
    got = tok([PROBE[0]])[0].tolist()
    want = PROBE[1] + [0] * (PREP_CONTEXT - len(PROBE[1]))
    if got != want:
        raise ExportError(
            f"model {name}'s tokenizer gives {got[:len(PROBE[1]) + 1]} for '{PROBE[0]}', "
            f"prep's gives {PROBE[1]}")
    return tok


def check_text_tower(model, name):
    """The text tower must read 77 ids of the 49408 vocabulary and pool at end-of-text."""
    for attr, want in (("context_length", PREP_CONTEXT), ("vocab_size", CLIP_VOCAB)):
        got = getattr(model, attr, want)
        if got != want:
            raise ExportError(f"model {name}'s text tower has {attr} {got}, expected {want}")
    text = getattr(model, "text", None)
    pool = getattr(model, "text_pool_type", None) or getattr(text, "pool_type", None)
    eos = getattr(model, "text_eos_id", None) or getattr(text, "eos_id", None)
    if not (pool == "argmax" or (pool == "eos" and eos == EOT)):
        raise ExportError(
            f"model {name}'s text tower pools with '{pool}' (eos id {eos}); with prep's "
            "zero-padded ids only argmax / end-of-text pooling reads the right token")


def check_image_size(size, name):
    size = side(size or 0)
    if size != (PREP_IMAGE_SIZE, PREP_IMAGE_SIZE):
        raise ExportError(
            f"model {name} takes {size[0]} x {size[1]} images; prep crops masks at "
            f"{PREP_IMAGE_SIZE} x {PREP_IMAGE_SIZE}: pick a 224 model (e.g. ViT-B-16, ViT-L-14)")


def build(torch, open_clip, args):
    # What can be refused from the configuration alone is refused before any weights load.
    config = open_clip.get_model_config(args.model)
    if config is None and not args.model.startswith("hf-hub:"):
        raise ExportError(f"open_clip has no model '{args.model}' (python -c 'import open_clip; "
                          "print(open_clip.list_models())' lists them)")
    config = config or {}
    if "image_size" in config.get("vision_cfg", {}):
        check_image_size(config["vision_cfg"]["image_size"], args.model)
    hf_tok = config.get("text_cfg", {}).get("hf_tokenizer_name")
    if hf_tok:
        raise ExportError(
            f"model {args.model} uses the Hugging Face tokenizer {hf_tok}; prep tokenises with "
            "OpenAI's CLIP BPE, so its text ids would mean nothing to this model")
    try:
        tok = check_tokenizer(open_clip, args.model)
    except ExportError:
        raise
    except Exception as e:  # an unknown model name, a hub tokenizer that cannot load
        raise ExportError(f"no open_clip tokenizer for {args.model}: {str(e).strip()[:200]}")
    pretrained = None if args.pretrained.lower() == "none" else args.pretrained
    force = {}
    if args.image_mean:
        force["mean"] = floats3(args.image_mean, "--image-mean")
    if args.image_std:
        force["std"] = floats3(args.image_std, "--image-std")
    if pretrained is None:
        torch.manual_seed(args.seed)
    try:
        model = open_clip.create_model(args.model, pretrained=pretrained, device="cpu",
                                     force_preprocess_cfg=force or None)
    except RuntimeError as e:  # unknown model / tag, a checkpoint that does not fit
        raise ExportError(f"open_clip cannot create {args.model} ({args.pretrained}): "
                          f"{str(e).splitlines()[0] if str(e) else type(e).__name__}")
    except (OSError, ValueError) as e:  # download or file problems
        raise ExportError(f"cannot load the weights '{args.pretrained}' of {args.model}: "
                          f"{str(e).splitlines()[0] if str(e) else type(e).__name__}")
    model.eval()
    visual = getattr(model, "visual", None)
    cfg = dict(getattr(visual, "preprocess_cfg", None) or {})
    check_image_size(cfg.get("size") or getattr(visual, "image_size", None), args.model)
    mean = tuple(float(x) for x in cfg.get("mean", open_clip.OPENAI_DATASET_MEAN))
    std = tuple(float(x) for x in cfg.get("std", open_clip.OPENAI_DATASET_STD))
    if any(s <= 0 for s in std):
        raise ExportError(f"image std {std} must be positive")
    check_text_tower(model, args.model)
    return model, tok, mean, std


def wrappers(torch, model, mean, std):
    # prep's input x = (p - PREP_MEAN) / PREP_STD; the model wants (p - mean) / std
    # = x * PREP_STD / std + (PREP_MEAN - mean) / std.
    scale = [ps / s for ps, s in zip(PREP_STD, std)]
    shift = [(pm - m) / s for pm, m, s in zip(PREP_MEAN, mean, std)]
    renorm = any(abs(a - 1.0) > 1e-7 for a in scale) or any(abs(b) > 1e-7 for b in shift)

    class Image(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.model = model
            self.register_buffer("scale", torch.tensor(scale).view(1, 3, 1, 1))
            self.register_buffer("shift", torch.tensor(shift).view(1, 3, 1, 1))

        def forward(self, pixel_values):
            if renorm:
                pixel_values = pixel_values * self.scale + self.shift
            return self.model.encode_image(pixel_values)

    class Text(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self, input_ids):
            return self.model.encode_text(input_ids)

    return Image().eval(), Text().eval(), renorm, scale, shift


def export(torch, module, example, path, input_name, output_name, opset):
    import warnings

    try:
        with warnings.catch_warnings():
            # The legacy exporter's deprecation notice and its advanced-indexing note (the
            # indices here are argmax positions, never negative).
            warnings.simplefilter("ignore")
            torch.onnx.export(
                module, (example,), path, dynamo=False, opset_version=opset,
                input_names=[input_name], output_names=[output_name],
                dynamic_axes={input_name: {0: "N"}, output_name: {0: "N"}})
    except Exception as e:  # the exporter's own errors are long; keep the first line
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ExportError(f"torch.onnx.export of {os.path.basename(path)} failed: {first}")


def unit(torch, y):
    return y / y.norm(dim=-1, keepdim=True)


def self_check(torch, image, text, tok, out):
    """Runs the ONNX files with onnxruntime against torch on a few inputs."""
    try:
        import numpy as np
        import onnxruntime as ort
    except ImportError:
        return {"skipped": "onnxruntime or numpy not installed"}
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 3, PREP_IMAGE_SIZE, PREP_IMAGE_SIZE, generator=g)
    ids = tok(["a photo of a fox", "the wall"])
    res = {}
    for name, module, inp, key in (("clip_image.onnx", image, x, "pixel_values"),
                                   ("clip_text.onnx", text, ids, "input_ids")):
        s = ort.InferenceSession(os.path.join(out, name), providers=["CPUExecutionProvider"])
        got = s.run(None, {key: inp.numpy()})[0]
        with torch.no_grad():
            want = module(inp).numpy()
        u = lambda a: a / np.linalg.norm(a, axis=1, keepdims=True)  # noqa: E731
        res[name] = float(np.abs(u(got) - u(want)).max())
    return {"max_abs_diff_normalised": res}


def reference(torch, model, tok, mean, std, rdir):
    import numpy as np

    wrote = []
    path = os.path.join(rdir, "image_in.f32")
    if os.path.exists(path):
        raw = np.fromfile(path, np.float32)
        n = raw.size // (3 * PREP_IMAGE_SIZE * PREP_IMAGE_SIZE)
        if n == 0 or raw.size != n * 3 * PREP_IMAGE_SIZE * PREP_IMAGE_SIZE:
            raise ExportError(f"{path}: {raw.size} floats, expected N x 3 x 224 x 224")
        x = raw.reshape(n, 3, PREP_IMAGE_SIZE, PREP_IMAGE_SIZE).astype(np.float64)
        pm, ps = np.array(PREP_MEAN)[None, :, None, None], np.array(PREP_STD)[None, :, None, None]
        mm, ms = np.array(mean)[None, :, None, None], np.array(std)[None, :, None, None]
        pixels = x * ps + pm  # back to 0..1, then the model's own normalisation
        xm = torch.from_numpy(((pixels - mm) / ms).astype(np.float32))
        with torch.no_grad():
            y = unit(torch, model.encode_image(xm)).numpy()
        y.astype(np.float32).tofile(os.path.join(rdir, "torch_image.f32"))
        wrote.append("torch_image.f32")
    path = os.path.join(rdir, "texts.txt")
    if os.path.exists(path):
        with open(path, encoding="utf-8") as f:
            texts = [t for t in f.read().split("\n") if t]
        if not texts:
            raise ExportError(f"{path} holds no text")
        ids = tok(texts)
        ids.numpy().astype(np.int64).tofile(os.path.join(rdir, "torch_ids.i64"))
        with torch.no_grad():
            y = unit(torch, model.encode_text(ids)).numpy()
        y.astype(np.float32).tofile(os.path.join(rdir, "torch_text.f32"))
        wrote += ["torch_ids.i64", "torch_text.f32"]
    return wrote


def main():
    p = argparse.ArgumentParser(
        description="Export an open_clip model's image and text encoders for prep "
                    "(--clip-image / --clip-text).")
    p.add_argument("--model", required=True, help="open_clip model name, e.g. ViT-B-32")
    p.add_argument("--pretrained", required=True,
                   help="open_clip pretrained tag (e.g. laion2b_s34b_b79k), a checkpoint file, "
                        "or 'none' (random weights: for tests)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--image-mean", help="override the model's image mean: a,b,c (0..1 scale)")
    p.add_argument("--image-std", help="override the model's image std: a,b,c")
    p.add_argument("--opset", type=int, default=17)
    p.add_argument("--seed", type=int, default=0, help="torch seed for --pretrained none")
    p.add_argument("--no-check", action="store_true", help="skip the onnxruntime self-check")
    p.add_argument("--reference", metavar="DIR",
                   help="also write torch's outputs on DIR/image_in.f32 and DIR/texts.txt")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    args = p.parse_args()
    torch, open_clip = import_modules()
    try:
        os.makedirs(args.out, exist_ok=True)
        torch.set_num_threads(max(1, min(4, os.cpu_count() or 1)))
        model, tok, mean, std = build(torch, open_clip, args)
        image, text, renorm, scale, shift = wrappers(torch, model, mean, std)
        x = torch.zeros(1, 3, PREP_IMAGE_SIZE, PREP_IMAGE_SIZE)
        ids = tok(["a photo of a fox"])
        with torch.no_grad():
            dim_i = image(x).shape[-1]
            dim_t = text(ids).shape[-1]
        if dim_i != dim_t:
            raise ExportError(f"image embeddings are {dim_i}-d but text ones {dim_t}-d")
        export(torch, image, x, os.path.join(args.out, "clip_image.onnx"),
               "pixel_values", "image_embeds", args.opset)
        export(torch, text, ids, os.path.join(args.out, "clip_text.onnx"),
               "input_ids", "text_embeds", args.opset)
        check = {"skipped": "--no-check"} if args.no_check else self_check(
            torch, image, text, tok, args.out)
        wrote = reference(torch, model, tok, mean, std, args.reference) if args.reference else []
        report = {
            "model": args.model,
            "pretrained": args.pretrained,
            "seed": args.seed if args.pretrained.lower() == "none" else None,
            "embed_dim": int(dim_i),
            "files": {"image": "clip_image.onnx", "text": "clip_text.onnx"},
            "image": {"input": "pixel_values [N,3,224,224] f32", "output": f"image_embeds [N,{dim_i}]",
                      "model_mean": mean, "model_std": std, "prep_mean": PREP_MEAN,
                      "prep_std": PREP_STD, "renormalised": renorm,
                      "renormalise_scale": scale if renorm else None,
                      "renormalise_shift": shift if renorm else None},
            "text": {"input": "input_ids [N,77] i64 (no attention_mask: causal text tower)",
                     "output": f"text_embeds [N,{dim_t}]", "tokenizer": type(tok).__name__,
                     "context": PREP_CONTEXT, "vocab": CLIP_VOCAB},
            "normalised_outputs": False,
            "opset": args.opset,
            "versions": {"torch": torch.__version__,
                         "open_clip": getattr(open_clip, "__version__", "?")},
            "check": check,
            "reference_files": wrote,
        }
        with open(os.path.join(args.out, "clip_export.json"), "w") as f:
            json.dump(report, f, indent=2)
        print(json.dumps({"out": args.out, "embed_dim": int(dim_i), "renormalised": renorm,
                          "check": check}))
    except ExportError as e:
        fail(str(e))
    except Exception as e:  # anything else: one line unless --debug
        if args.debug:
            raise
        fail(f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''} "
             "(rerun with --debug for the traceback)")


if __name__ == "__main__":
    main()
