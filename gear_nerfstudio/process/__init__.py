"""`ns-gear-process`: synchronised videos of a camera rig -> a Neural 3D Video scene (`camXX.mp4` + `poses_bounds.npy`)."""
