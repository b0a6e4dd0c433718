"""testing: synthetic scenes for tests and benchmarks (no stage imports this package).

May import: `stages.core`, `stages.scene`, `stages.render`.
"""
