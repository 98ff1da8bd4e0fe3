"""Nonlinear least squares shared by the client and the server: bundle adjustment of keyframe
poses and map points with GTSAM (:mod:`.bundle`), in a worker process or in-process, and the one
Levenberg-Marquardt / Gauss-Newton loop of the numpy solvers (:mod:`.lm`)."""
