"""Models: the rigid-body coarse model fitted by Levenberg-Marquardt and the fine (hybrid) network,
its training and the pre-trained baseline. Imports physics, artifacts, runtime; imported by stages."""
