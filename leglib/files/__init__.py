"""Measurement files: the thesis's CSV plus a JSON sidecar, committed as one unit, read strictly.

:mod:`~leglib.files.atomic` writes files that appear whole or not at all;
:mod:`~leglib.files.names` says what a file's name holds; :mod:`~leglib.files.measurements`
writes and reads measurements and batches; :mod:`~leglib.files.claims` gives one writer per
point; :mod:`~leglib.files.sweepdir` lists a sweep's directory, sets unfinished writes aside
and checks the directory's provenance.
"""
