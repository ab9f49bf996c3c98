"""Studies described by scene files (``parjam run``), one module per concept:

- :mod:`parjam.study.scene`: the scene model and its validation (TOML -> :class:`Scene`);
- :mod:`parjam.study.plan`: the stages a scene needs, their keys, solvers and estimates;
- :mod:`parjam.study.records`: the per-state work of an analysis stage (calls the physics);
- :mod:`parjam.study.runner`: the stages member by member over groups of ranks, resumable;
- :mod:`parjam.study.summary`: the summary file format, written by the runner and read by the
  plots (parjam.plot.paper, parjam.plot.spectra).
"""
