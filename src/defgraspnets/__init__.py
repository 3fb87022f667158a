"""defgraspnets: deformable-object grasp simulation, learning and planning, and soft tactile sensing.

Subpackages (see DESIGN.md):

- :mod:`defgraspnets.fem`       quasi-static finite elements in NVIDIA Warp (the one physics engine)
- :mod:`defgraspnets.objects`   procedural and real object meshes, tetrahedralization
- :mod:`defgraspnets.grasp`     parallel-jaw gripper, antipodal sampling, grasp experiments and metrics
- :mod:`defgraspnets.tactile`   simulated depth-camera membrane sensor and tactile algorithms
- :mod:`defgraspnets.data`      HDF5 schemas, datasets and datamodules
- :mod:`defgraspnets.models`    DefGraspNets (MeshGraphNets) and the wrench CNN
- :mod:`defgraspnets.planning`  differentiable grasp objectives, scoring and refinement
- :mod:`defgraspnets.eval`      metrics, generalization splits and reports
"""

__version__ = "0.1.0"
