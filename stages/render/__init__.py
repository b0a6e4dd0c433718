"""render: turning Gaussians into pixels, with the standard 3DGS semantics.

Owns: spherical harmonics (`sh`), projection to 2D Gaussians (`projection`), tile binning
(`tiles`), the compositing walk and the blend weights it yields (`composite`), the `Rasterizer`
front end (`rasterizer`), the slow float64 twin the tests hold the kernels to (`reference`), and
the optional gsplat GPU backend (`gsplat_backend`), which is injected into a `Rasterizer`, never
imported by it. May import: `stages.core`, `stages.scene`.
"""
