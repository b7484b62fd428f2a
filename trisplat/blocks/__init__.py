"""Scenes bigger than one machine: the scene cut into blocks (partition), one ordinary trisplat run per block as a
Ray task (run_ray), and the blocks merged into one connected surface in a normal run folder (merge)."""
