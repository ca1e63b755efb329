"""What the notebooks use beyond the public API: the parameters check and metrics
(:mod:`~leglib.notebook.setup`), widgets (:mod:`~leglib.notebook.widgets`), the live view
(:mod:`~leglib.notebook.liveview`), papermill runs (:mod:`~leglib.notebook.run`), batch
re-runs (:mod:`~leglib.notebook.batch`) and the command line (:mod:`~leglib.notebook.cli`)."""

from . import deferred as _deferred

_deferred.install()   # jsonschema's IRI checks load on their first use (a second or more of every process that runs notebooks)
