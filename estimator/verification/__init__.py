"""After the mixture: the leading rotation hypotheses checked against the edges of every kept
view, and the winner's full pose refined over them (the chamfer to the image's edges)."""
