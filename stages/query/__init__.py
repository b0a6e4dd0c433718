"""query: from a text prompt to the Gaussians of interest, masks and edited PLYs.

Owns: prompts and their embeddings (`prompts`), the OSH as pure math (`osh`), RES mask sources
(`res`), the hyperplanes artifact and the fitting step (`hyperplanes`), masks and overlays
(`masks`), the 3D selection artifact (`selection`), PLY edits (`export_ply`) and the chained
query (`pipeline`). May import: `stages.core`, `stages.scene`, `stages.render`,
`stages.semantics`.
"""
