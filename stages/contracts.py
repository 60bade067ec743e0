"""Every stage's artifacts in pipeline order, and ``docs/artifacts.md`` rendered from them.

```
python -m stages.contracts > docs/artifacts.md
```

Each stage declares what it writes in ``stages/<stage>/artifacts.py`` (its ``ARTIFACTS``); a test fails when the
committed ``docs/artifacts.md`` differs from this rendering.
"""

from __future__ import annotations

import importlib
import sys

from pipeline.contracts import ArtifactSet, render_markdown
from stages import REGISTRY

TITLE = "Artifacts"
INTRO = """
What each stage writes into its folder of a run (`RUN/<stage>/`), rendered from the declarations in
`stages/<stage>/artifacts.py` (`python -m stages.contracts > docs/artifacts.md`; a test keeps this file current).
Stages write and read these files only through the declarations: writing casts to the declared types and fails on
a missing or undeclared column; reading checks the columns and names the stage to re-run when a run folder is older
than the code. Every stage also writes `summary.json` (its headline numbers, the runner's record) and a recording
`RUN/<stage>.rrd`. Positions and poses are in the map frame, stamps on the bag clock.
"""


def artifact_sets() -> list[ArtifactSet]:
    """The ``ARTIFACTS`` of every stage that declares them, in pipeline order."""
    sets = []
    for stage in REGISTRY.names:
        sets.append(importlib.import_module(f"stages.{stage}.artifacts").ARTIFACTS)
    return sets


def render() -> str:
    """The content of ``docs/artifacts.md``."""
    return render_markdown(TITLE, INTRO, artifact_sets())


if __name__ == "__main__":
    sys.stdout.write(render())
