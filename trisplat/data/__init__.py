"""Capture loaders: load_dataset(path) -> SceneData, format detected from the folder."""
from trisplat.data.loader import detect_format, detect_formats, load_dataset
from trisplat.data.options import LoadOptions
from trisplat.data.types import SceneData

__all__ = ["LoadOptions", "SceneData", "detect_format", "detect_formats", "load_dataset"]
