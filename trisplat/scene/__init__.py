"""The triangle table being optimised (TriangleScene), spherical harmonics, and initial triangles."""
