"""The stages of focusmap, in pipeline order, and the estimation maths they share.

Each stage module exposes ``STAGE: Final[Stage]``; :data:`REGISTRY` lists them in order.
"""

from __future__ import annotations

from typing import Final

from pipeline.registry import Registry
from stages import detect, evaluate, graph, ingest, optimize, select_landmarks, select_measurements

REGISTRY: Final = Registry(
    [
        ingest.STAGE,
        detect.STAGE,
        graph.STAGE,
        select_landmarks.STAGE,
        select_measurements.STAGE,
        optimize.STAGE,
        evaluate.STAGE,
    ]
)
