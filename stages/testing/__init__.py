"""testing: synthetic scenes (`synthetic`) and randomly initialised RES checkpoints (`models`)
for tests and benchmarks (no stage imports this package).

May import: `stages.core`, `stages.scene`, `stages.render`.
"""
