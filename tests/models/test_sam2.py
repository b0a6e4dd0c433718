"""SAM 2 (transformers Sam2Model) as a bundle's SAM: the export split into an image side with
three maps and a box decoder, its numpy pre- and post-processing against transformers' own
arithmetic, the whole OWLv2 + SAM 2 pipeline against torch, and the RES split with SAM 2's maps
in the index.

Sam2ImageProcessor needs torchvision, which has no CPU wheel here: its resize is
`F.interpolate(uint8, mode="bilinear", antialias=True)` and its mask post-processing
`F.interpolate(mode="bilinear", align_corners=False)` (transformers' image_processing_sam2),
which the references below call directly."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from goi_cli.main import main
from stages.core.errors import GoiError
from stages.models import res_processing as rp
from stages.models.bundle import load_bundle
from stages.testing import models as M
from tests.models.split_check import owl_split_equals_ground

transformers = pytest.importorskip("transformers")

PROMPTS = ("a red chair", "the green sofa", "the lamp")


@pytest.fixture(scope="module")
def sam2_checkpoint(tmp_path_factory):
    return M.save_checkpoint(M.sam2(), tmp_path_factory.mktemp("sam2") / "sam2")


@pytest.fixture(scope="module")
def owl_sam2(res_checkpoints, sam2_checkpoint, tmp_path_factory):
    out = tmp_path_factory.mktemp("owl-sam2") / "b"
    argv = ["export-model", str(res_checkpoints["owlv2"]), str(sam2_checkpoint), "--out",
            str(out), "--box-threshold", "0.3", "--max-boxes", "3"]  # fmt: skip
    assert main(argv) == 0
    return out


def _torch_pixels(rgb, size, mean, std):
    """Sam2ImageProcessor's arithmetic: uint8 bilinear antialiased resize, /255, normalise."""
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].contiguous()
    x = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    x = x.float() / 255
    return ((x - torch.tensor(mean)[:, None, None]) / torch.tensor(std)[:, None, None]).numpy()


@pytest.mark.parametrize("hw", [(96, 128), (130, 90), (480, 640)])
def test_sam2_inputs_equal_the_processors_within_a_grey_level(hw):
    rgb = np.random.default_rng(hw[0]).integers(0, 256, (*hw, 3), dtype=np.uint8)
    got = rp.sam2_inputs(rgb, 256)
    want = _torch_pixels(rgb, 256, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    assert got.shape == want.shape == (1, 3, 256, 256)
    level = 1 / 255 / min(rp.IMAGENET_STD)
    assert np.abs(got - want).max() <= level + 1e-5
    assert np.mean(np.abs(got - want) > 1e-5) < 0.02  # rounding ties only


def test_sam2_boxes_and_masks_equal_sam2processor():
    from transformers.models.sam2.processing_sam2 import Sam2Processor

    boxes = np.asarray([[10, 20, 300, 240], [0.5, 7.25, 639, 479]], np.float32)
    want = Sam2Processor._normalize_coordinates(
        None, 1024, torch.from_numpy(boxes), (480, 640), is_bounding_box=True
    )
    assert np.abs(rp.sam2_boxes(boxes, (480, 640), 1024)[0] - want.numpy()).max() <= 1e-4
    low = np.random.default_rng(0).normal(0, 5, (2, 64, 64)).astype(np.float32)
    want = F.interpolate(torch.from_numpy(low)[None], (96, 130), mode="bilinear",
                         align_corners=False)[0].numpy()  # fmt: skip
    assert np.abs(rp.sam2_mask_logits(low, (96, 130)) - want).max() <= 1e-5


def _reference(ck_owl, ck_sam2, bundle, rgb, text):
    """OWLv2's boxes from goi (held to transformers by test_owl.py), then torch's Sam2Model on
    the processor's pixels and box coordinates, its masks post-processed as post_process_masks
    does: the union of the boxes' masks."""
    boxes, _ = bundle._owl_sam.detect(bundle._owl_sam._owl(rgb), rgb.shape[:2],
                                      bundle.res_prompt(text))  # fmt: skip
    model = transformers.Sam2Model.from_pretrained(
        str(ck_sam2), attn_implementation="eager", use_safetensors=True
    ).eval()
    pixels = _torch_pixels(rgb, 128, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    from transformers.models.sam2.processing_sam2 import Sam2Processor

    coords = Sam2Processor._normalize_coordinates(
        None, 128, torch.from_numpy(boxes), rgb.shape[:2], is_bounding_box=True
    )
    with torch.no_grad():
        out = model(pixel_values=torch.from_numpy(pixels), input_boxes=coords[None],
                    multimask_output=False)  # fmt: skip
    masks = F.interpolate(out.pred_masks[0], rgb.shape[:2], mode="bilinear", align_corners=False)
    return boxes, (masks[:, 0] > 0).any(0).numpy()


def test_owl_sam2_bundle_equals_torch(res_checkpoints, sam2_checkpoint, owl_sam2):
    bundle = load_bundle(owl_sam2)
    m = json.loads((owl_sam2 / "manifest.json").read_text())
    assert m["schema_version"] == "1.4"
    assert m["owl_sam"]["sam_decoder"]["layout"] == "sam2"
    for name in ("sam_encoder.onnx", "sam_decoder.onnx"):  # checked against torch at export
        assert m["export_checks"][name]["max_abs_error"] < 1e-3
    # every Hiera block's attention, the q-pooling ones too, runs as onnxruntime's fused op
    onnx = pytest.importorskip("onnx")
    ops = [n.op_type for n in onnx.load(owl_sam2 / "sam_encoder.onnx").graph.node]
    assert (
        ops.count("MultiHeadAttention")
        == 5
        == m["export_checks"]["sam_encoder.onnx"]["fused_attention"]
    )
    assert "Softmax" not in ops
    rng = np.random.default_rng(11)
    found = 0
    for hw in ((96, 128), (130, 90)):
        rgb = rng.integers(0, 256, (*hw, 3), dtype=np.uint8)
        for text in PROMPTS:
            boxes, want = _reference(res_checkpoints["owlv2"], sam2_checkpoint, bundle, rgb, text)
            got = bundle.ground(rgb, text)
            assert np.array_equal(got.boxes, boxes)
            found += len(boxes)
            # the resize differs from torchvision's by a grey level at a few pixels
            assert np.mean(got.mask != want) <= 0.005
    assert found > 0


def test_owl_sam2_split_keeps_sam2s_maps_in_the_index(owl_sam2):
    bundle = load_bundle(owl_sam2)
    assert bundle.res_indexable
    spec = bundle.res_image_side_spec()
    assert spec["sam_embedding"] == ((32, 8, 8), "float16")
    assert spec["sam_high_res_0"] == ((4, 32, 32), "float16")
    assert spec["sam_high_res_1"] == ((8, 16, 16), "float16")
    side = owl_split_equals_ground(bundle, PROMPTS, 0.005)  # float16 maps, as stored
    del side["sam_high_res_1"]
    with pytest.raises(GoiError, match="'sam_high_res_1' is missing"):
        bundle.res_from_image_side(side, (130, 90), bundle.res_prompt("the lamp"))


def test_a_grounded_bundle_takes_sam2_too(res_checkpoints, sam2_checkpoint, tmp_path):
    out = tmp_path / "b"
    argv = ["export-model", str(res_checkpoints["detector"]), str(sam2_checkpoint), "--out",
            str(out), "--detector-height", "96", "--detector-width", "128",
            "--box-threshold", "0.0", "--max-boxes", "2"]  # fmt: skip
    assert main(argv) == 0
    bundle = load_bundle(out)
    rgb = np.random.default_rng(3).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    want = bundle.ground(rgb, "a red chair")
    assert len(want.boxes) == 2 and 0 < want.mask.mean() < 1
    side = {k: v[0] for k, v in bundle._grounded.sam.embed(rgb).items()}
    got = bundle.res_from_image_side(side, (96, 128), bundle.res_prompt("a red chair"), rgb)
    assert np.array_equal(got.mask, want.mask)


def test_sam21s_video_checkpoints_export_as_the_image_model(
    res_checkpoints, sam2_checkpoint, owl_sam2, tmp_path
):
    """facebook/sam2.1-hiera-* ship as Sam2VideoModel checkpoints (model_type sam2_video): the
    same weights in that layout give the same bundle."""
    image = transformers.Sam2Model.from_pretrained(str(sam2_checkpoint), use_safetensors=True)
    cfg = image.config
    video = transformers.Sam2VideoModel(
        transformers.Sam2VideoConfig(
            vision_config=cfg.vision_config.to_dict(),
            prompt_encoder_config=cfg.prompt_encoder_config.to_dict(),
            mask_decoder_config=cfg.mask_decoder_config.to_dict(),
            image_size=128,
        )
    )
    missing, _ = video.load_state_dict(image.state_dict(), strict=False)
    assert all(k not in image.state_dict() for k in missing)  # only the memory modules
    ck = M.save_checkpoint(video, tmp_path / "sam2.1-video")
    assert json.loads((ck / "config.json").read_text())["model_type"] == "sam2_video"
    out = tmp_path / "b"
    argv = ["export-model", str(res_checkpoints["owlv2"]), str(ck), "--out", str(out),
            "--box-threshold", "0.3", "--max-boxes", "3"]  # fmt: skip
    assert main(argv) == 0
    got, want = load_bundle(out), load_bundle(owl_sam2)
    rgb = np.random.default_rng(2).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    found = 0
    for text in PROMPTS:
        a, b = got.ground(rgb, text), want.ground(rgb, text)
        assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.mask, b.mask)
        found += int(b.mask.sum())
    assert found > 0


def test_sam2_refusals(res_checkpoints, sam2_checkpoint, owl_sam2, tmp_path, capsys):
    argv = ["export-model", str(res_checkpoints["owlv2"]), str(sam2_checkpoint), "--out",
            str(tmp_path / "x"), "--sam-size", "64"]  # fmt: skip
    assert main(argv) == 2
    assert "--sam-size" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    root = tmp_path / "b"
    import shutil

    shutil.copytree(owl_sam2, root)
    m = json.loads((root / "manifest.json").read_text())
    m["owl_sam"]["sam_decoder"]["high_res"] = ["high_res_feat_s0", "nope"]
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(GoiError, match="sam_decoder.onnx: no input named 'nope'"):
        load_bundle(root).check_res()
    del m["owl_sam"]["sam_decoder"]["high_res"]
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(GoiError, match="'owl_sam.sam_decoder.high_res' needs the two"):
        load_bundle(root)
