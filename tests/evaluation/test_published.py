"""The published figures beside goi's: every row cites its source and protocol, its values are
the tables' (percentages / 100), and the page shows them."""

import numpy as np
import pytest

from stages.evaluation.benchmarks.common import BenchmarkScene, Query
from stages.evaluation.benchmarks.page import benchmark_page
from stages.evaluation.benchmarks.published import OTHERS, published_rows
from stages.evaluation.benchmarks.scoring import PROTOCOLS


@pytest.mark.parametrize("benchmark", ["lerf-ovs", "lerf-mask", "3d-ovs"])
def test_every_row_names_protocol_source_and_where_it_was_read(benchmark):
    metrics = set(PROTOCOLS[benchmark][1])
    for r in OTHERS[benchmark]:
        assert r.protocol and r.source and r.read_in
        assert r.method in ("LangSplat", "LangSplatV2", "Gaussian Grouping")
        for figs in r.figures.values():
            assert set(figs) <= metrics
            assert all(0 < v < 1 for v in figs.values())


def test_the_tables_values_and_the_protocol_difference():
    mean = {(label, proto[:30]): f for label, proto, f in published_rows("lerf-ovs", "mean")}
    own = [f for (lab, p), f in mean.items() if lab == "LangSplat (published)" and "Lang" in p]
    assert own == [{"miou": 0.514, "localisation_accuracy": 0.843}]
    og = [f for (lab, p), f in mean.items() if p.startswith("OpenGaussian")]
    assert og == [{"miou": 0.0966}]  # the same method under OpenGaussian's protocol
    v2 = published_rows("lerf-ovs", "waldo_kitchen")[1]
    assert v2[0] == "LangSplatV2 (published)" and v2[2]["localisation_accuracy"] == 0.955
    gg = published_rows("lerf-mask", "ramen")[0]
    assert gg[0] == "Gaussian Grouping (published)" and gg[2] == {
        "miou": 0.77,
        "boundary_miou": 0.687,
    }
    assert "arXiv 2312.00732" in gg[1] and "read in:" in gg[1]
    assert published_rows("3d-ovs", "room")[0][2] == {"miou": 0.584}  # ObjectGS's only
    assert published_rows("lerf-ovs", "no-such-scene") == []
    # the GOI paper's own tables stay
    assert published_rows("goi-m360", "mean")[-1][2]["miou"] == 0.8646


def _doc(scenes: dict[str, float]) -> dict:
    """A lerf-mask report of one variant over `scenes` ({scene: goi's mIoU})."""

    def figs(x):
        return {
            "protocol": {"miou": x, "boundary_miou": x / 2},
            "goi": {"miou": x, "mpa": x, "mp": x},
        }

    per = {
        sc: {"n_frames": 1, "n_queries": 1, "skipped": [], "frames": {"0": "v0"},
             "variants": {"full": {**figs(x), "queries": {"q": {"0": {"iou": x}}}}}}
        for sc, x in scenes.items()
    }  # fmt: skip
    mean = float(np.mean(list(scenes.values())))
    return {
        "room": "bench", "goi_version": "0", "threshold": 0.5, "timings_s": {},
        "metric_notes": {"how_goi_enters": "mask", "goi": "goi"},
        "benchmark": {"name": "lerf-mask", "protocol": PROTOCOLS["lerf-mask"][0], "scenes": per},
        "variants": {"full": figs(mean)},
    }  # fmt: skip


def test_published_means_only_over_the_same_scenes(tmp_path):
    scenes = {"figurines": 0.5, "ramen": 0.7, "myroom": 0.9}
    bench = {sc: BenchmarkScene(sc, tmp_path, [Query("q", "q")], []) for sc in scenes}
    page = tmp_path / "p.html"
    benchmark_page(page, _doc(scenes), bench, {})
    html = page.read_text()
    mean3 = html.split("<h2>Mean over 3 scene(s)</h2>")[1].split("<h2>")[0]
    assert "(published" not in mean3  # no published mean covers figurines, ramen and myroom
    two = html.split("<h2>Mean over the 2 published scenes given (figurines, ramen)</h2>")[1]
    two = two.split("<h2>")[0]
    assert "<td>0.6000</td>" in two  # goi's mean over figurines and ramen
    assert "<td>0.7335</td>" in two and "0.7280" not in html  # GG's two scenes, not its three
    assert "Gaussian Grouping (published; mean of its 2 per-scene figure(s))" in two
    assert "Published figures shown: Gaussian Grouping, LangSplat," in html
    assert "LangSplatV2" not in html.split("Published figures shown:")[1].split(",")[1]
    benchmark_page(page, _doc({"figurines": 0.5, "ramen": 0.7, "teatime": 0.6}), bench | {
        "teatime": BenchmarkScene("teatime", tmp_path, [Query("q", "q")], [])}, {})  # fmt: skip
    mean3 = page.read_text().split("<h2>Mean over 3 scene(s)</h2>")[1].split("<h2>")[0]
    assert "<td>0.7280</td>" in mean3 and "its printed mean over 3" in mean3  # the same three
    benchmark_page(page, _doc({"myroom": 0.9}), {"myroom": bench["myroom"]}, {})
    assert (
        "none was published for the scenes given (myroom); lerf-mask has published figures "
        "for figurines, ramen, teatime" in page.read_text()
    )
