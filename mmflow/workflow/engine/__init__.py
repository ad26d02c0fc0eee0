"""The engine: the runner, the run directory, the task context, fingerprints, task keys, clusters and
the helpers every stage shares (time chunks, blocks, reductions, geometry).
"""
