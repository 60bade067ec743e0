"""Export a finished run's map and trajectory in the formats other tools load (``focusmap export``).

Public API (in :mod:`stages.export.writers`): ``FORMATS`` and ``export_run(run_dir, stage, fmt, out)``.
"""
