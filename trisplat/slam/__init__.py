"""RGB-D SLAM with triangles (ALGORITHM.md section 5): track each frame's pose through the differentiable renderer,
map keyframes into a triangle soup, output a TUM trajectory, the model and a connected mesh."""
