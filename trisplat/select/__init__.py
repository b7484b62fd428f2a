"""Object selection: faces of an object from 2D masks, and splitting a mesh into object and remainder."""
from trisplat.select.extract import FaceVotes, count_votes, extract_faces, face_id_maps, fill_hidden_faces
from trisplat.select.masks import match_masks, read_mask
from trisplat.select.split import MeshPart, split_mesh, submesh

__all__ = [
    "FaceVotes",
    "MeshPart",
    "count_votes",
    "extract_faces",
    "face_id_maps",
    "fill_hidden_faces",
    "match_masks",
    "read_mask",
    "split_mesh",
    "submesh",
]
