"""pytest-xdist's ``loadgroup`` scheduling with a spare worker (tests/conftest.py): the spare
one takes only the tests ``takes`` allows; the other workers take every other test, and the
spare one's too once nothing else is left; each in the collection's order (the slow first)."""

from __future__ import annotations

from xdist.scheduler import LoadGroupScheduling


class SpareScheduling(LoadGroupScheduling):
    def __init__(self, config, log=None, *, spare: str, takes):
        super().__init__(config, log)
        self.spare, self.takes = spare, takes
        self._spare_scopes = {}

    def _for_spare(self, scope: str) -> bool:
        if scope not in self._spare_scopes:
            self._spare_scopes[scope] = all(self.takes(nodeid) for nodeid in self.workqueue[scope])
        return self._spare_scopes[scope]

    def _assign_work_unit(self, node) -> None:
        """One unit of work (a test, or an xdist_group's tests) to ``node``: for the spare
        worker the first it may take (none left: it is told to stop, and runs the tests it
        holds first; a worker holds back its last test until it gets more or is told to
        stop); for another worker the first the spare one may not take, else the first left."""
        assert self.workqueue
        if node.gateway.id == self.spare:
            scope = next((s for s in self.workqueue if self._for_spare(s)), None)
            if scope is None:
                node.shutdown()
                return
        else:
            scope = next((s for s in self.workqueue if not self._for_spare(s)), next(iter(self.workqueue)))
        work_unit = self.workqueue.pop(scope)
        self.assigned_work.setdefault(node, {})[scope] = work_unit
        collection = self.registered_collections[node]
        node.send_runtest_some([collection.index(nodeid) for nodeid, done in work_unit.items() if not done])
