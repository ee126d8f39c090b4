"""Physics: sun position, geodesy, actuator laws, heliostat kinematics, its Jacobian, the
Levenberg-Marquardt solver and the error metrics. Pure functions of arrays/tensors; imports nothing
of heliocal but :mod:`heliocal.pipeline.errors`. Everyone may import it."""
