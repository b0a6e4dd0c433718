"""OWLv2 split into an image graph and a text graph (goi export-model), the class logits in
numpy equal to transformers' model + post-processing, and OWLv2 + SAM behind the RES split."""

import json
import shutil

import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.core.errors import GoiError
from stages.models import res_processing as rp
from stages.models.bundle import load_bundle
from stages.models.export.attention import fuse_attention
from stages.models.onnx_io import session
from tests.models.split_check import owl_split_equals_ground

transformers = pytest.importorskip("transformers")


@pytest.fixture(scope="module")
def owl_bundle(res_checkpoints, tmp_path_factory):
    out = tmp_path_factory.mktemp("owl") / "owl-sam"
    argv = ["export-model", str(res_checkpoints["owlv2"]), str(res_checkpoints["sam"]),
            "--out", str(out), "--box-threshold", "0.3", "--max-boxes", "3"]  # fmt: skip
    assert main(argv) == 0
    return out


def _torch(ck, pixels, ids):
    model = transformers.Owlv2ForObjectDetection.from_pretrained(
        str(ck), attn_implementation="eager", use_safetensors=True
    ).eval()
    with torch.no_grad():
        return model(
            input_ids=torch.from_numpy(ids),
            pixel_values=torch.from_numpy(pixels),
            attention_mask=torch.ones(ids.shape, dtype=torch.long),
        )


@pytest.mark.parametrize("hw,text", [((48, 64), "a red chair"), ((70, 40), "the blue lamp")])
def test_split_detector_equals_transformers_post_processing(res_checkpoints, owl_bundle, hw, text):
    """Image graph + text graph + numpy logits and boxes == Owlv2ForObjectDetection +
    Owlv2ImageProcessor.post_process_object_detection on the same pixels."""
    bundle = load_bundle(owl_bundle)
    owl = bundle._owl_sam
    rgb = np.random.default_rng(hw[0]).integers(0, 256, (*hw, 3), dtype=np.uint8)
    spec = bundle.manifest["owl_sam"]["image"]
    pixels = rp.owl_inputs(rgb, 64, tuple(spec["mean"]), tuple(spec["std"]))
    prompt = bundle.res_prompt(text)
    out = _torch(res_checkpoints["owlv2"], pixels, prompt.ids)
    logits = out.logits[0, :, 0].numpy()
    side = owl._owl(rgb)
    got = rp.owl_logits(side["owl_class_embeds"], side["owl_logit_shift"],
                        side["owl_logit_scale"], prompt.embedding)  # fmt: skip
    assert np.abs(got - logits).max() <= 1e-4 * max(1.0, np.abs(logits).max())
    assert np.abs(side["owl_boxes"] - out.pred_boxes[0].numpy()).max() <= 1e-5
    assert np.abs(side["owl_objectness"] - out.objectness_logits[0].numpy()).max() <= 1e-4
    thr = float(np.median(1 / (1 + np.exp(-logits))))  # half of the patches pass
    proc = transformers.Owlv2ImageProcessorPil()
    want = proc.post_process_object_detection(out, threshold=thr, target_sizes=[hw])[0]
    order = torch.argsort(want["scores"], descending=True, stable=True)
    boxes, scores = rp.owl_detections(got, side["owl_boxes"], hw, thr, 1000)
    assert len(scores) == len(order) > 0
    assert np.abs(scores - want["scores"][order].numpy()).max() <= 1e-5
    assert np.abs(boxes - want["boxes"][order].numpy()).max() <= 1e-3  # pixels


def test_owl_sam_split_equals_ground(owl_bundle):
    bundle = load_bundle(owl_bundle)
    assert bundle.res_kind == "owl_sam" and bundle.res_indexable
    spec = bundle.res_image_side_spec()
    assert spec == {
        "owl_class_embeds": ((16, 32), "float16"),
        "owl_logit_shift": ((16,), "float32"),
        "owl_logit_scale": ((16,), "float32"),
        "owl_boxes": ((16, 4), "float32"),
        "owl_objectness": ((16,), "float32"),
        "sam_embedding": ((32, 8, 8), "float16"),
    }
    owl_split_equals_ground(bundle, ("a red chair", "the green sofa", "the lamp"), 2e-3)


def test_owl_image_graph_runs_fused_attention(owl_bundle, res_checkpoints, tmp_path):
    onnx = pytest.importorskip("onnx")
    config = json.loads((res_checkpoints["owlv2"] / "config.json").read_text())
    layers = config["vision_config"]["num_hidden_layers"]
    ops = [n.op_type for n in onnx.load(owl_bundle / "owl_image.onnx").graph.node]
    m = json.loads((owl_bundle / "manifest.json").read_text())
    # every layer's scores in one blockwise kernel; the split test holds it to transformers
    assert ops.count("MultiHeadAttention") == layers == 2
    assert m["export_checks"]["owl_image.onnx"]["fused_attention"] == layers
    assert "Softmax" not in ops and "Attention" not in ops
    # the same checkpoints give the same fused file, byte for byte
    again = tmp_path / "again"
    argv = ["export-model", str(res_checkpoints["owlv2"]), str(res_checkpoints["sam"]),
            "--out", str(again), "--box-threshold", "0.3", "--max-boxes", "3"]  # fmt: skip
    assert main(argv) == 0
    assert (again / "owl_image.onnx").read_bytes() == (owl_bundle / "owl_image.onnx").read_bytes()
    # a graph with no self-attention of its pattern is left byte for byte
    text = tmp_path / "owl_text.onnx"
    shutil.copy(owl_bundle / "owl_text.onnx", text)
    before = text.read_bytes()
    assert fuse_attention(text, 2, 32) == 0
    assert text.read_bytes() == before


def test_owl_exports_are_checked_and_bad_manifests_refused(owl_bundle, tmp_path):
    m = json.loads((owl_bundle / "manifest.json").read_text())
    assert set(m["export_checks"]) == {
        "owl_image.onnx", "owl_text.onnx", "sam_encoder.onnx", "sam_decoder.onnx"
    }  # fmt: skip
    names = [o.name for o in session(owl_bundle / "owl_image.onnx").get_outputs()]
    assert names == ["class_embeds", "logit_shift", "logit_scale", "pred_boxes", "objectness"]
    root = tmp_path / "b"
    shutil.copytree(owl_bundle, root)

    def refused(edit, match):
        bad = json.loads(json.dumps(m))
        edit(bad)
        (root / "manifest.json").write_text(json.dumps(bad))
        with pytest.raises(GoiError, match=match):
            load_bundle(root).check_res()

    refused(lambda b: b["owl_sam"].update(box_threshold=1.5), "'owl_sam.box_threshold' is 1.5")
    refused(lambda b: b["owl_sam"]["image"].update(size=[64, 48]), "must be square")
    refused(lambda b: b["owl_sam"]["image"].update(size=[96, 96]),
            "'pixel_values' has size 64 on axis 2, expected 96")  # fmt: skip
    refused(lambda b: b["owl_sam"]["image"].update(std=[0, 1, 1]), "'owl_sam.image.std'")
    refused(lambda b: b["owl_sam"]["text"].update(file="../x.onnx"), "outside the bundle")
    refused(lambda b: b.update(grounded={}), "'grounded.detector' is missing")
    refused(lambda b: b["owl_sam"]["sam_decoder"].update(layout="segment-anything"),
            "no input named 'point_coords'")  # fmt: skip


def test_export_plans_with_owl_are_refused_when_incomplete(res_checkpoints, tmp_path, capsys):
    ck = res_checkpoints
    for sources, words in (
        ([ck["owlv2"]], ("owlv2", "needs a SAM checkpoint")),
        ([ck["owlv2"], ck["detector"], ck["sam"]], ("one RES", "owlv2", "grounding-dino")),
    ):
        capsys.readouterr()
        assert main(["export-model", *map(str, sources), "--out", str(tmp_path / "b")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and all(w in err for w in words), err
        assert not (tmp_path / "b").exists()
