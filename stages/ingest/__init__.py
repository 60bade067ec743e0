"""Stage ``ingest``: read a recording into the run folder (see ``ARTIFACTS.md`` for what it writes)."""

from stages.ingest.stage import STAGE, IngestConfig

__all__ = ["STAGE", "IngestConfig"]
