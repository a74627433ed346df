"""Evaluation: the harness that dances baselines and ablations (``harness``) and its HTML report
(``report``). ``ROWS`` lives here so the CLI can list them without importing the harness."""

#: ChoreoMaster's Table-3 rows, in table order (see ``harness``).
ROWS: tuple[str, ...] = (
    "real",
    "random_walk",
    "clip_concat",
    "ours",
    "no_style",
    "no_rhythm",
    "no_structure",
)
