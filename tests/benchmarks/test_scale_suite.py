"""The scale suite runs end to end (at a toy size) and reports every key the issue names."""

import pytest

from benchmarks.scale import Size, suite_scale

KEYS = {
    "scale_cache_build_s",
    "scale_cache_disk_gib",
    "scale_fit_field_s",
    "scale_peak_rss_gib",
    "scale_render_mask_s",
    "scale_new_prompt_s",
}


@pytest.mark.slow
def test_the_scale_suite_reports_its_figures(tmp_path):
    figures = suite_scale(1, tmp_path, Size(gaussians=20_000, views=6, width=160, height=120,
                                            iterations=20))  # fmt: skip
    assert KEYS <= set(figures)
    assert all(figures[k] > 0 for k in KEYS)
    assert figures["scale_gaussians"] == 20_000 and figures["scale_pixels"] == 160 * 120
    # the process's own peak, not the benchmark's: a 20k-Gaussian fit is far below 1 GiB... of
    # data, though Python, torch and numba alone take a few hundred MiB
    assert figures["scale_peak_rss_gib"] < 2
