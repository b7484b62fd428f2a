"""Capture loaders: load_dataset(path) -> SceneData, format detected from the folder."""
