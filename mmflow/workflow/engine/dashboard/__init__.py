"""mmflow's page in the dask dashboard (``/mmflow``): the run's stages against its plan.

The driver (:mod:`mmflow.workflow.engine.runner`) tells a :class:`~mmflow.workflow.engine.dashboard.board.RunBoard`
what it does (stages begun, tasks finished, stages done); the page
(:mod:`mmflow.workflow.engine.dashboard.page`, a route of the scheduler's own HTTP server) reads it together
with the scheduler's view of the workers. Local and SLURM/PBS clusters run their scheduler in the
driver's process, so the page sees the board directly; a cluster joined by address has its
scheduler elsewhere and no mmflow page (docs/clusters.md).

:mod:`.board` is light (no dask import): the runner imports it for synchronous runs too.
"""
