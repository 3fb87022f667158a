"""Simulated depth-camera soft tactile sensor (membrane on the FEM engine, interior depth camera) and
tactile algorithms: contact regions, force models, contour following, learning from demonstration."""
