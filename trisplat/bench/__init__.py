"""Benchmarks: `trisplat bench render | train | mesh`, each writing JSON and a markdown table with machine facts."""
