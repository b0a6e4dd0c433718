"""The rasterisation rules of INRIA's CUDA rasteriser, shared by every kernel and the reference.

EWA projection cov2d = J W Sigma W^T J^T + 0.3 I, radius ceil(3 sqrt(lambda_max)), 16x16 tiles,
front-to-back compositing in depth order, alpha = min(0.99, o exp(-q/2)), alpha < 1/255
skipped, and a pixel stops before the Gaussian that would bring its transmittance T below 1e-4.
Features are composited without a background term.
"""

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
NEAR = 0.2  # INRIA's frustum cull: nothing closer than 0.2 to the camera plane is drawn
