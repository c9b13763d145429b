"""Taking a trained run elsewhere: the Gaussians at a time as a standard 3DGS PLY (``pidg export``), and opening a
run for such tools with one-line errors (a folder that is not a run, a time outside [0, 1])."""
from pidg.export.ply import (
    DEFAULT_SH_DEGREE,
    SplatFrame,
    export_ply,
    export_ply_sequence,
    ply_property_names,
    sequence_times,
    splat_frame,
    write_splat_ply,
)
from pidg.export.run_model import check_run_folder, check_time, open_run_model

__all__ = [
    "DEFAULT_SH_DEGREE",
    "SplatFrame",
    "check_run_folder",
    "check_time",
    "export_ply",
    "export_ply_sequence",
    "open_run_model",
    "ply_property_names",
    "sequence_times",
    "splat_frame",
    "write_splat_ply",
]
