"""core: what every layer uses and nothing of goi's own beneath it.

Owns: the user-error type and warnings (`errors`), atomic artifact files, HDF5/JSON writing and
reading, digests and provenance (`artifacts`), the reporting callback stages speak through
(`report`) and small array helpers (`arrays`). May import: the standard library, numpy, h5py and
`schemas`. Never click: the CLI supplies the terminal side of `report`.
"""
