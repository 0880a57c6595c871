"""Rendering: shading and images of a BVH or a scene, on top of the queries."""
