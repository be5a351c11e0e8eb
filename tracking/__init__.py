"""TrackDeform3D keypoint tracking as pure functions on numpy arrays."""
