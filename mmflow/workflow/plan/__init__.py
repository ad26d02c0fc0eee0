"""The planner: what a run will cost per stage (:mod:`mmflow.workflow.plan.planner`), the constants fitted to
measured runs (:mod:`mmflow.workflow.plan.fit`) and the records of those runs (``records/``).
"""
