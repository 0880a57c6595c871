"""Verification: what runs builds and queries to check them: the float64 oracle,
the test meshes, the hard cases, ``lbvh check``, the self-test, the kernel variants."""
