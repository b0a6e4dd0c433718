"""evaluation: the pipeline on benchmark rooms, scored as the paper scores it, and the demo.

Owns: the paper's metrics (`metrics`), the room format (`room`), the ablation variants
(`variants`), `goi eval` (`pipeline`), the HTML pages (`report`) and `goi demo` (`demo`).
May import every layer below: core, scene, render, semantics, query.
"""
