"""What every step shares: SE(3)/SO(3) geometry, the camera model, the object catalog and its
symmetries, and the root error class."""
