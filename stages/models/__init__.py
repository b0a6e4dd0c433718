"""models: the foundation models goi runs, as ONNX bundles, and their exports.

Owns: model bundles (`bundle`, with `manifest` checking every manifest value and `onnx_io`
opening their ONNX graphs), their export from Hugging Face checkpoints or segment-anything ONNX
files (`export/`), the RES models' pre- and post-processing (`res_processing`) and the RES
pipelines, each split into an image side (once per image, what a RES index stores) and a prompt
side: Grounded-SAM and SAM in both ONNX layouts (`grounded`), OWLv2 + SAM (`owl`) and CLIPSeg
(`clipseg`). Nothing here knows the semantic field: `semantics` runs a bundle's image encoder
to make feature maps, `query` runs its text encoder and RES models. May import: `stages.core`,
`stages.scene`, `stages.render`.
"""
