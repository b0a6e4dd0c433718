"""scene: what a pretrained 3DGS scene is made of, read from and written to disk.

Owns: the INRIA PLY (`gaussians`), quaternions and rotations (`rotation`), pinhole cameras
(`cameras`) with one small reader/writer per format (`formats/`), images and masks (`images`),
and the scene directory with its train/test split (`scene`). May import: `stages.core`.
"""
