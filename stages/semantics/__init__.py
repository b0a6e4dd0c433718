"""semantics: the 3D Gaussian semantic field and everything it is fitted from.

Owns: feature maps and their import/encoding (`features`, `feature_files`, `extract`, which runs a
bundle's image encoder from `stages.models`), the codebook (TFCC) and its k-means (`kmeans`,
`codebook`), the frozen-geometry blend cache (`weights`, `blend_cache`) and the sparse feature
renderer on it (`feature_renderer`), the field (`field`: artifact; `field_model`: model and losses;
`fit_field`: the training loop; `checkpoint`), and decoding a rendered field to codebook entries
(`decode`). May import: `stages.core`, `stages.scene`, `stages.render`, `stages.models`.
"""
