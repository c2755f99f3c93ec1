"""The HIL plant: a pybullet arm behind emulated CiA 402 drives."""
