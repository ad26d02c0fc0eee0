"""The configuration: the schema (:mod:`mmflow.workflow.config.schema`), its base model, the errors a user
reads and the checks made before any work.
"""
