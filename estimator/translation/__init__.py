"""Step one of the method (paper, section III-B): each object's 3D translation as a Gaussian
fused from the per-view 2D centers: association of a view's centers with the tracks, founding
of tracks from two views, splitting of views a track cannot explain, merging of tracks that
converged."""
