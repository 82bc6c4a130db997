"""``sarah-bench``: speed of prep, loading and generation against naive references, one run.

Outside the model package on purpose (like nanoGPT's bench.py): the library never depends on
it. ``config.py`` (what runs, the goals), ``bench.py`` (the run), ``naive.py`` (the reference
streamer), ``data.py`` (prep, loader, HuBERT), ``report.py`` (verdicts, report, history row)."""
