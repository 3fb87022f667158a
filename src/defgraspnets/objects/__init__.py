"""Object geometry: procedural primitives, real-world meshes shipped by pip packages, tetrahedralization with a disk cache."""
