"""`goi eval --benchmark`: the public open-vocabulary 3DGS benchmarks (LERF-OVS, LERF-Mask,
3D-OVS, GOI's Mip-NeRF360 set, Replica as GOI scores it), each read and scored exactly as its
reference code does (../shared/notes/public-benchmarks.md): `common` (what a reader returns),
one reader per benchmark, `protocols` (the metrics), `published` (figures from the papers),
`run` (the orchestration) and `page` (the HTML)."""
