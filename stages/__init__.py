"""goi's stages: each module does one step of the GOI pipeline; the CLI only parses and reports."""

__version__ = "0.1.0"
