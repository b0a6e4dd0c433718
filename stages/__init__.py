"""goi's stages, layered along the data's path. Each layer imports only the layers below it
(checked by the import-linter contract in pyproject.toml):

    evaluation | inspect | testing    benchmark rooms, metrics, reports, the demo; artifact checks;
                                      synthetic scenes for tests and benchmarks
    query                             prompts, the OSH, RES sources, masks, selections, PLY edits
    semantics                         features, model bundles, codebook, blend cache, the field
    render                            the rasteriser (numba), its reference twin, optional gsplat
    scene                             PLY, cameras (one reader/writer per format), images, scenes
    core                              errors, artifacts and provenance, the report callback

Pure math (arrays in, arrays out) sits in its own modules, apart from file I/O and from the
orchestration that strings steps together; the CLI (goi_cli) only parses, calls and reports.
"""

__version__ = "0.1.0"
