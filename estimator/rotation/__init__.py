"""Step two of the method (paper, section III-C): with the translation known, each view's
rotation from LINE-2D templates rendered at one canonical distance (the scale-aware re-crop,
the renderer, the template banks, the matching) fused in a max-mixture over SO(3)."""
