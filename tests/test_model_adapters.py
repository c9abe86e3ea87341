"""The real-model adapters run end to end through their libraries (opt-in: ``pytest -m models``).

No weights are downloaded: every test builds a tiny randomly initialised model from a config
(kornia ``LoFTR(pretrained=None)``, a YOLO from ultralytics' bundled yaml, a MobileSAM from
ultralytics' builder, a tiny diffusers inpainting pipeline, tiny transformers / open_clip
CLIPs), saves it in ``tmp_path`` the way a user's local weights would be laid out, and drives
the adapter through its protocol method. A random model says nothing about accuracy, so the
assertions are about the contract: shapes, dtypes, value ranges, unit norms, masks of the image
size, determinism, and the few behaviours a random network does show (identical inputs give
identical features, so LoFTR finds mutual nearest neighbours between an image and itself).

Each test skips, naming the missing package, when its library is not importable.
"""

from __future__ import annotations

import json
import os
import string

import numpy as np
import pytest

pytestmark = pytest.mark.models

# hub-aware libraries must fail rather than reach for the network; ultralytics writes a
# settings file at import, keep it out of $HOME
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


def _need(*modules: str):
    """Import ``modules`` or skip the test with the pip names to install."""
    pip = {"open_clip": "open_clip_torch"}
    out = []
    for m in modules:
        out.append(pytest.importorskip(m, reason=f"'{m}' is not installed (pip install {pip.get(m, m)}); "
                                                 "these tests run the real library"))
    return out[0] if len(out) == 1 else out


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth random colour texture (H, W, 3) float32 in [0, 1] (blobs at several scales)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.float32)
    for s in (4, 8, 16):
        img += cv2.resize(rng.random((max(2, h // s), max(2, w // s), 3)).astype(np.float32), (w, h),
                          interpolation=cv2.INTER_CUBIC)
    img -= img.min()
    return (img / img.max()).astype(np.float32)


def _clip_tokenizer_files(d) -> tuple[str, str]:
    """A character-level CLIP BPE vocabulary (no merges) covering lower-case text."""
    d = str(d)
    os.makedirs(d, exist_ok=True)
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in string.ascii_lowercase + string.digits + ".,!?'-:;()":
        vocab.setdefault(c, len(vocab))
        vocab.setdefault(c + "</w>", len(vocab))
    vf, mf = os.path.join(d, "vocab.json"), os.path.join(d, "merges.txt")
    with open(vf, "w") as f:
        json.dump(vocab, f)
    with open(mf, "w") as f:
        f.write("#version: 0.2\n")
    return vf, mf


_VISION = dict(image_size=32, patch_size=8, hidden_size=32, intermediate_size=37, num_attention_heads=4,
               num_hidden_layers=2)


# -------------------------------------------------------------------------------------------
# LoFTR (kornia)
# -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def loftr_ckpt(tmp_path_factory):
    torch = _need("torch")
    _need("kornia")
    from kornia.feature import LoFTR

    torch.manual_seed(0)
    net = LoFTR(pretrained=None)
    d = tmp_path_factory.mktemp("loftr")
    path = d / "loftr_random.ckpt"
    torch.save({"state_dict": net.state_dict()}, path)  # the layout of the official checkpoints
    lightning = d / "loftr_lightning.ckpt"  # the reference implementation's key prefix
    torch.save({"state_dict": {"matcher." + k: v for k, v in net.state_dict().items()}, "epoch": 0}, lightning)
    return str(path), str(lightning)


def test_loftr_matcher_counts(loftr_ckpt):
    from splatsearch.plugins import make_matcher
    from splatsearch.search import LoFTRMatcher, Matcher

    goal = _texture(120, 160, seed=1)
    noise = np.random.default_rng(2).random((96, 128, 3)).astype(np.float32)
    raw = make_matcher(f"loftr:{loftr_ckpt[0]},conf_thresh=0.0,model=none,max_side=160")
    assert isinstance(raw, LoFTRMatcher) and isinstance(raw, Matcher) and raw.model is None
    same, other = raw.count(goal, goal), raw.count(goal, noise)
    assert isinstance(same, int) and isinstance(other, int) and other >= 0
    # identical inputs give identical features on both sides, so mutual nearest neighbours
    # exist; before conf_thresh reached LoFTR's own coarse threshold (0.2) a random model
    # returned none at any conf_thresh
    assert same > 0
    assert same >= other
    assert raw.count(goal, goal) == same  # deterministic

    verified = LoFTRMatcher(loftr_ckpt[0], conf_thresh=0.0, max_side=160)  # + RANSAC (fundamental)
    v = verified.count(goal, goal)
    assert isinstance(v, int) and 0 <= v <= same
    assert verified.count(goal, goal) == v


def test_loftr_reads_lightning_checkpoint_and_rejects_bad_input(loftr_ckpt):
    from splatsearch.search import LoFTRMatcher

    m = LoFTRMatcher(loftr_ckpt[1], conf_thresh=0.0, model=None, max_side=64)
    img = _texture(64, 64, seed=3)
    ref = LoFTRMatcher(loftr_ckpt[0], conf_thresh=0.0, model=None, max_side=64)
    assert m.count(img, img) == ref.count(img, img)  # same weights, prefix stripped
    with pytest.raises(ValueError, match="shape"):
        m.count(img, img[..., 0])


# -------------------------------------------------------------------------------------------
# YOLO (+ SAM) through ultralytics
# -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def yolo_models(tmp_path_factory):
    d = tmp_path_factory.mktemp("yolo")
    os.environ.setdefault("YOLO_CONFIG_DIR", str(d / "config"))
    torch = _need("torch")
    _need("torchvision")
    ultralytics = _need("ultralytics")
    from ultralytics.models.sam.build import build_mobile_sam

    torch.manual_seed(0)
    seg = d / "yolov8n-seg-random.pt"
    ultralytics.YOLO("yolov8n-seg.yaml").save(str(seg))  # the yaml ships with ultralytics
    box = d / "yolov8n-random.pt"
    ultralytics.YOLO("yolov8n.yaml").save(str(box))
    sam_dir = d / "sam"
    sam_dir.mkdir()
    sam = sam_dir / "mobile_sam.pt"  # ultralytics picks the SAM architecture from the file name
    net = build_mobile_sam(checkpoint=None)
    # a random IoU head predicts values around 0 whose sign flips with the image; pin it to 0.1
    # (a poor mask, as a real SAM rates a bad prompt) so what the adapter keeps is reproducible
    last = net.mask_decoder.iou_prediction_head.layers[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(0.1)
    torch.save(net.state_dict(), sam)
    return str(seg), str(box), str(sam)


# a yaml-built YOLO names its 80 classes "0".."79"
_ALL_TO_GOALS = {str(i): g for i, g in enumerate(["chair", "sofa", "table", "tv_monitor", "plant", "bed"] * 14)}


def _check_dets(dets, shape, labels):
    from splatsearch.search import Detection, check_detections

    assert isinstance(dets, list)
    check_detections(dets, shape, "test")
    for d in dets:
        assert isinstance(d, Detection)
        assert d.mask.dtype == bool and d.mask.shape == shape and d.n_pixels >= 1
        assert d.label in labels and 0.0 <= d.score <= 1.0


def _same(a, b) -> bool:
    return len(a) == len(b) and all(x.label == y.label and x.score == y.score and np.array_equal(x.mask, y.mask)
                                    for x, y in zip(a, b))


def test_yolo_seg_detector(yolo_models):
    from splatsearch.plugins import make_detector
    from splatsearch.search import Detector, UltralyticsDetector

    rgb = _texture(100, 130, seed=4)  # not a multiple of YOLO's stride 32: masks must be resized back
    det = UltralyticsDetector(yolo_models[0], class_map=_ALL_TO_GOALS, conf=0.0, min_pixels=1, imgsz=160, max_det=8)
    assert isinstance(det, Detector)
    dets = det.detect(rgb)
    _check_dets(dets, (100, 130), set(_ALL_TO_GOALS.values()))
    assert len(dets) <= 8
    assert _same(dets, det.detect(rgb))  # deterministic
    assert _same(det.detect(rgb.astype(np.float64), frame=object()), dets)  # frame is ignored

    # a random YOLO's class scores are ~1e-4 (its head's prior), so the default conf keeps none,
    # and a class map that maps nothing drops everything
    assert UltralyticsDetector(yolo_models[0], class_map=_ALL_TO_GOALS, imgsz=160).detect(rgb) == []
    assert UltralyticsDetector(yolo_models[0], conf=0.0, min_pixels=1, imgsz=160).detect(rgb) == []  # COCO names

    # through the plug-in spec, with the goal classes restricted
    spec = make_detector(f"yolo:{yolo_models[0]},conf=0.0,min_pixels=1,imgsz=160,max_det=8",
                         goal_classes=("chair",))
    assert isinstance(spec, UltralyticsDetector) and spec.max_det == 8 and spec.imgsz == 160


def test_yolo_box_only_detector_fills_boxes(yolo_models):
    from splatsearch.search import UltralyticsDetector

    rgb = _texture(100, 130, seed=5)
    det = UltralyticsDetector(yolo_models[1], class_map=_ALL_TO_GOALS, conf=0.0, min_pixels=1, imgsz=160, max_det=6)
    dets = det.detect(rgb)
    _check_dets(dets, (100, 130), set(_ALL_TO_GOALS.values()))
    assert 1 <= len(dets) <= 6  # conf=0 keeps every box NMS leaves; a box is never empty at min_pixels=1
    for d in dets:  # without SAM a box-only model's mask is its filled box
        rows, cols = np.nonzero(d.mask)
        assert d.n_pixels == (np.ptp(rows) + 1) * (np.ptp(cols) + 1)


def test_yolo_with_mobile_sam_masks(yolo_models):
    from splatsearch.search import UltralyticsDetector

    rgb = _texture(100, 130, seed=5)
    kw = dict(class_map=_ALL_TO_GOALS, conf=0.0, min_pixels=1, imgsz=160, max_det=6)
    boxes = UltralyticsDetector(yolo_models[1], **kw).detect(rgb)
    det = UltralyticsDetector(yolo_models[1], sam_weights_path=yolo_models[2], **kw)
    dets = det.detect(rgb)
    _check_dets(dets, (100, 130), set(_ALL_TO_GOALS.values()))
    # one mask per box, in the boxes' order: labels and scores are the box-only run's, less any
    # box whose random SAM mask is empty. SAM's predicted IoU (0.1) is below ultralytics' default
    # conf (0.25), which used to drop every mask (and pair any survivors with the wrong boxes)
    it = iter([(d.label, d.score) for d in boxes])
    assert dets and all(any(p == q for q in it) for p in [(d.label, d.score) for d in dets])
    assert all(not np.array_equal(d.mask, b.mask) for d, b in zip(dets, boxes))  # SAM's masks, not boxes
    assert _same(dets, det.detect(rgb))


# -------------------------------------------------------------------------------------------
# diffusers inpainting pipeline
# -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def inpaint_pipeline(tmp_path_factory):
    torch = _need("torch")
    _need("diffusers")
    _need("transformers")
    from diffusers import AutoencoderKL, DDIMScheduler, StableDiffusionInpaintPipeline, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    d = tmp_path_factory.mktemp("diffusion")
    vf, mf = _clip_tokenizer_files(d / "tok")
    tok = CLIPTokenizer(vf, mf, model_max_length=32)
    torch.manual_seed(0)
    unet = UNet2DConditionModel(block_out_channels=(32, 64), layers_per_block=1, sample_size=16, in_channels=9,
                                out_channels=4, down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
                                up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"), cross_attention_dim=32,
                                attention_head_dim=8, norm_num_groups=16)
    vae = AutoencoderKL(block_out_channels=(16, 32), in_channels=3, out_channels=3,
                        down_block_types=("DownEncoderBlock2D",) * 2, up_block_types=("UpDecoderBlock2D",) * 2,
                        latent_channels=4, norm_num_groups=16, sample_size=32)
    text = CLIPTextModel(CLIPTextConfig(vocab_size=len(tok), hidden_size=32, intermediate_size=37,
                                        num_attention_heads=4, num_hidden_layers=2, max_position_embeddings=32,
                                        bos_token_id=0, eos_token_id=1, pad_token_id=1))
    sched = DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
                          set_alpha_to_one=False, steps_offset=1)
    pipe = StableDiffusionInpaintPipeline(vae=vae, text_encoder=text, tokenizer=tok, unet=unet, scheduler=sched,
                                          safety_checker=None, feature_extractor=None, requires_safety_checker=False)
    path = d / "pipeline"
    pipe.save_pretrained(str(path))
    return str(path)


def test_diffusion_inpainter(inpaint_pipeline):
    from splatsearch.plugins import make_inpainter
    from splatsearch.search import DiffusionInpainter, Inpainter

    inp = make_inpainter(f"diffusion:{inpaint_pipeline},prompt=a chair,num_inference_steps=2")
    assert isinstance(inp, DiffusionInpainter) and isinstance(inp, Inpainter)
    images = np.stack([_texture(36, 44, seed=6), _texture(36, 44, seed=7)])  # not multiples of 8
    masks = np.zeros((2, 36, 44), bool)
    masks[0, 10:22, 8:30] = True  # view 1 has no hole
    out = inp.inpaint(images, masks)
    assert out.shape == images.shape and out.dtype == np.float32
    assert np.all(np.isfinite(out)) and out.min() >= 0.0 and out.max() <= 1.0
    np.testing.assert_array_equal(out[~masks], images[~masks])  # only holes change
    np.testing.assert_array_equal(out[1], images[1])
    assert not np.array_equal(out[0][masks[0]], images[0][masks[0]])  # the hole was repainted
    np.testing.assert_array_equal(inp.inpaint(images, masks), out)  # seeded: reproducible
    with pytest.raises(ValueError, match="masks"):
        inp.inpaint(images, masks[:, :-1])


# -------------------------------------------------------------------------------------------
# image encoders (transformers CLIP / SigLIP / BLIP-2 / plain ViT, open_clip) and appearance
# -------------------------------------------------------------------------------------------

def _save_transformers(kind: str, d) -> tuple[str, int]:
    """A tiny random ``kind`` model + image processor saved in ``d``; returns (dir, embedding D)."""
    import torch
    import transformers as T

    torch.manual_seed(0)
    text = dict(vocab_size=100, hidden_size=32, intermediate_size=37, num_attention_heads=4, num_hidden_layers=2,
                max_position_embeddings=64, bos_token_id=0, eos_token_id=1, pad_token_id=1)
    square = {"height": 32, "width": 32}
    if kind == "clip":
        model = T.CLIPModel(T.CLIPConfig(text_config=text, vision_config=_VISION, projection_dim=16))
        proc, dim = T.CLIPImageProcessor(size={"shortest_edge": 32}, crop_size=square), 16
    elif kind == "siglip":
        model = T.SiglipModel(T.SiglipConfig(text_config=text, vision_config=_VISION))
        proc, dim = T.SiglipImageProcessor(size=square), 32
    elif kind == "blip2":
        opt = T.OPTConfig(vocab_size=100, hidden_size=32, num_hidden_layers=2, ffn_dim=37, num_attention_heads=4,
                          max_position_embeddings=64, word_embed_proj_dim=32)
        qformer = dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=4, intermediate_size=37,
                       vocab_size=100, encoder_hidden_size=32)
        # Blip2VisionConfig's default initializer_range is 1e-10 (real weights replace it): the
        # random tower would map every image to one vector
        vision = dict(_VISION, initializer_range=0.02)
        model = T.Blip2Model(T.Blip2Config(vision_config=vision, qformer_config=qformer, text_config=opt.to_dict(),
                                           num_query_tokens=4))
        proc, dim = T.BlipImageProcessor(size=square), 32
    elif kind == "vit":
        model = T.ViTModel(T.ViTConfig(**_VISION))
        proc, dim = T.ViTImageProcessor(size=square), 32
    else:
        raise ValueError(kind)
    model.save_pretrained(str(d))
    proc.save_pretrained(str(d))
    return str(d), dim


def _check_encoder(enc, dim: int):
    from splatsearch.nav.encoders import ImageEncoder

    assert isinstance(enc, ImageEncoder)
    a, b = _texture(50, 70, seed=8), _texture(40, 40, seed=9)
    ea = enc.embed(a)
    assert ea.shape == (dim,) and ea.dtype == np.float32 and np.all(np.isfinite(ea))
    assert np.linalg.norm(ea) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_array_equal(enc.embed(a), ea)  # deterministic
    eu8 = enc.embed((a * 255).round().astype(np.uint8))  # uint8 input reads as the same image
    np.testing.assert_allclose(eu8, ea, atol=1e-5)
    eb = enc.embed(b)
    assert eb.shape == (dim,) and not np.allclose(eb, ea)
    with pytest.raises(ValueError, match="rgb"):
        enc.embed(a[..., 0])


@pytest.mark.parametrize("kind", ["clip", "siglip", "blip2", "vit"])
def test_transformers_image_encoder(kind, tmp_path):
    _need("torch")
    _need("transformers")
    from splatsearch.plugins import make_encoder
    from splatsearch.nav.encoders import TransformersImageEncoder

    path, dim = _save_transformers(kind, tmp_path / kind)
    enc = make_encoder(f"transformers:{path}")
    assert isinstance(enc, TransformersImageEncoder)
    # CLIP's embedding is the projected one (projection_dim), the space its text tower shares
    _check_encoder(enc, dim)


@pytest.fixture(scope="module")
def open_clip_tiny(tmp_path_factory):
    torch = _need("torch")
    _need("torchvision")
    open_clip = _need("open_clip")

    d = tmp_path_factory.mktemp("open_clip")
    name = "splatsearch-tiny-test"
    cfg = {"embed_dim": 16,
           "vision_cfg": {"image_size": 32, "layers": 2, "width": 32, "head_width": 16, "patch_size": 8},
           # open_clip's bundled BPE tokenizer has 49408 tokens
           "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 32, "heads": 2, "layers": 2}}
    with open(d / f"{name}.json", "w") as f:
        json.dump(cfg, f)
    open_clip.add_model_config(str(d / f"{name}.json"))  # registers the architecture by file stem
    torch.manual_seed(0)
    ckpt = d / "tiny_open_clip.pt"
    torch.save(open_clip.create_model(name).state_dict(), ckpt)
    return str(ckpt), name


def test_open_clip_encoder(open_clip_tiny):
    from splatsearch.plugins import make_encoder
    from splatsearch.nav.encoders import OpenCLIPEncoder

    enc = make_encoder(f"openclip:{open_clip_tiny[0]},model_name={open_clip_tiny[1]}")
    assert isinstance(enc, OpenCLIPEncoder)
    _check_encoder(enc, 16)


def test_encoder_appearance_over_a_real_encoder(tmp_path):
    _need("torch")
    _need("transformers")
    from splatsearch.nav.encoders import TransformersImageEncoder
    from splatsearch.search import AppearanceModel, EncoderAppearance

    path, dim = _save_transformers("clip", tmp_path / "clip")
    app = EncoderAppearance(TransformersImageEncoder(path))
    assert isinstance(app, AppearanceModel)
    rgb = _texture(80, 100, seed=10)
    mask = np.zeros((80, 100), bool)
    mask[20:50, 30:45] = True  # smaller than min_size: the crop is padded
    sig = app.signature(rgb, mask)
    assert sig.shape == (dim,) and sig.dtype == np.float32 and np.linalg.norm(sig) == pytest.approx(1.0, abs=1e-5)
    assert app.similarity(sig, sig) == pytest.approx(1.0, abs=1e-6)
    other = app.signature(_texture(80, 100, seed=11), mask)
    assert 0.0 <= app.similarity(sig, other) <= 1.0
    empty = app.signature(rgb, np.zeros_like(mask))
    assert empty.shape == (dim,) and not empty.any() and app.similarity(sig, empty) == 0.0


# -------------------------------------------------------------------------------------------
# CLIP context classifier (CoNVOI), both backends
# -------------------------------------------------------------------------------------------

def _save_clip_with_tokenizer(d) -> str:
    import torch
    import transformers as T

    vf, mf = _clip_tokenizer_files(d)
    tok = T.CLIPTokenizer(vf, mf, model_max_length=128)  # character tokens: prompts are ~70 long
    proc = T.CLIPProcessor(image_processor=T.CLIPImageProcessor(size={"shortest_edge": 32},
                                                                crop_size={"height": 32, "width": 32}),
                           tokenizer=tok)
    torch.manual_seed(0)
    text = dict(vocab_size=len(tok), hidden_size=32, intermediate_size=37, num_attention_heads=4,
                num_hidden_layers=2, max_position_embeddings=128, bos_token_id=0, eos_token_id=1, pad_token_id=1)
    model = T.CLIPModel(T.CLIPConfig(text_config=text, vision_config=_VISION, projection_dim=16))
    model.save_pretrained(str(d))
    proc.save_pretrained(str(d))
    return str(d)


def _check_context(clf):
    from splatsearch.social import CONTEXTS, ContextClassifier, ContextResult

    assert isinstance(clf, ContextClassifier)
    img = _texture(60, 80, seed=12)
    res = clf.classify(img)
    assert isinstance(res, ContextResult)
    assert list(res.probs) == list(CONTEXTS)
    p = np.array(list(res.probs.values()))
    assert np.all((p >= 0) & (p <= 1)) and p.sum() == pytest.approx(1.0, abs=1e-5)
    assert res.label == max(res.probs, key=res.probs.get)
    assert clf.classify(img).probs == res.probs  # deterministic
    assert isinstance(clf.is_paved(img[:20, :20]), bool)
    with pytest.raises(ValueError, match="image"):
        clf.classify(None)


def test_clip_context_classifier_transformers(tmp_path):
    _need("torch")
    _need("transformers")
    from splatsearch.social import CLIPContextClassifier

    clf = CLIPContextClassifier(_save_clip_with_tokenizer(tmp_path / "clip"))
    assert clf.backend == "transformers"
    _check_context(clf)


def test_clip_context_classifier_open_clip(open_clip_tiny):
    from splatsearch.social import CLIPContextClassifier

    clf = CLIPContextClassifier(open_clip_tiny[0], model_name=open_clip_tiny[1])
    assert clf.backend == "open_clip"
    _check_context(clf)
