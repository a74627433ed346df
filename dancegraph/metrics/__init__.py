"""Evaluation metrics, arrays in and numbers out: ``beats`` (beat accuracy, Beat Align Scores),
``smoothness`` (seams vs the library), ``physical`` (foot skating, stage), ``structure``
(repeat/mirror pairs, controls, signature χ²), ``kinetic`` (FID_k), ``diversity``."""
