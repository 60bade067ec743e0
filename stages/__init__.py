"""The stages of focusmap, in pipeline order, and the estimation maths they share.

Each stage package exposes ``STAGE: Final[Stage]``; :data:`REGISTRY` lists them in order. Importing this
package imports only the stages' settings models and descriptions: a stage's code, and the numerics it
uses, are imported when it runs (or when a public name of its package is first used).
"""

from __future__ import annotations

from typing import Final

from pipeline.registry import Headline, Registry
from stages import detect, evaluate, graph, ingest, optimize, select_landmarks, select_measurements

HEADLINES: Final = {
    "landmarks": Headline("int64", (("graph", "landmarks"),), "lms"),
    "focused_landmarks": Headline(
        "int64", (("select_landmarks", "selected"), ("optimize", "focused_landmarks")), "foc"
    ),
    "measurements_kept": Headline(
        "int64", (("select_measurements", "selected"), ("optimize", "tag_measurements")), "kept"
    ),
    "focused_entropy": Headline(
        "float64",
        (
            ("optimize", "focused_entropy"),
            ("select_measurements", "entropy_after"),
            ("evaluate", "headline.focused_entropy"),
        ),
        "H",
    ),
    "max_collision_probability": Headline(
        "float64",
        (
            ("optimize", "max_collision_probability"),
            ("select_landmarks", "p_collision_max_focused"),
            ("evaluate", "headline.max_collision_probability"),
        ),
        "maxP",
    ),
    "collision_rate": Headline("float64", (("evaluate", "headline.collision_rate"),), "rate"),
    "graph_warnings": Headline("int64", (("graph", "health.warnings"),), "warn"),
}
"""The figures ``focusmap batch`` shows per run: column -> where to find it in the stage summaries."""

REGISTRY: Final = Registry(
    [
        ingest.STAGE,
        detect.STAGE,
        graph.STAGE,
        select_landmarks.STAGE,
        select_measurements.STAGE,
        optimize.STAGE,
        evaluate.STAGE,
    ],
    HEADLINES,
    {
        "ingest": "ing",
        "detect": "det",
        "graph": "gra",
        "select_landmarks": "s-lm",
        "select_measurements": "s-ms",
        "optimize": "opt",
        "evaluate": "eva",
    },
)
