"""view: `goi view`, the scene and a prompt's answers in the browser, on viser.

Owns: what the browser is sent (`splats`: the Gaussians as splats, chunked, and the colours of
each highlight mode; `cameras`: the browser's camera as a goi Camera and back), the viewer's
state without any browser (`session`: the routes a prompt can take, their answers, the answer
history, the mask at a camera, the exports), the one worker every answer runs on (`worker`),
and the viser front end (`app`). Only `app` imports viser (the optional extra `goi[view]`).
"""
