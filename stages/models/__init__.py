"""models: the foundation models goi runs, as ONNX bundles, and their exports.

Owns: model bundles (`bundle`, with `onnx_io` opening their ONNX graphs), their export from
Hugging Face checkpoints (`export/`), the RES models' pre- and post-processing (`res_processing`)
and the Grounded-SAM pipeline (`grounded`: detector -> SAM -> union). Nothing here knows the
semantic field: `semantics` runs a bundle's image encoder to make feature maps, `query` runs its
text encoder and RES models. May import: `stages.core`, `stages.scene`, `stages.render`.
"""
