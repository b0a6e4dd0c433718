"""The published figures beside goi's: every row cites its source and protocol, its values are
the tables' (percentages / 100), and the page shows them."""

import pytest

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
