"""A workaround for a lost wake-up in the Jupyter client stack (nbclient#312,
jupyter_client#1059, both open upstream), in its own module so it goes when they are fixed.

jupyter_client's ``Session.send`` writes through a *blocking* shadow of a channel's
``zmq.asyncio`` socket. That send processes the socket's pending commands, which drains the
socket's edge-triggered file descriptor, and ``zmq.asyncio`` is not told: when a message
(a cell's ``execute_reply``) came in just before, the ``poll()`` nbclient awaits for it never
wakes, although the message sits readable in the socket (later messages on the same pipe
raise no new edge either). nbclient sends on the shell while it awaits a cell's reply
whenever the cell writes into an ``ipywidgets.Output`` (its Output-widget mimic syncs each
output back to the kernel), as the notebooks' slider panels do: the run then waits for the
cell timeout with kernel and client both idle (two notebook-04 runs at once hung 10 times in
20, more often under load). Reading ``EVENTS`` through the asyncio socket after each send
makes pyzmq schedule its event handling when a message is pending.

leglib's runs (:func:`leglib.notebook.run.execute`, ``make run``, batches) give nbclient
:class:`RearmingKernelManager`; a run from the papermill command line takes the same fix with
``papermill --engine leglib ...`` (:class:`Engine`, registered as papermill's engine
``leglib`` by the package's entry point).

``tests/notebook/test_wakeup.py`` reproduces the bug without the workaround at the versions
of :data:`CHECKED_WITH`; when an upgrade fixes it upstream, that test fails and this module
can go.
"""

from __future__ import annotations

import zmq
from jupyter_client.asynchronous import AsyncKernelClient
from jupyter_client.manager import AsyncKernelManager
from traitlets import DottedObjectName, Type

# the versions the lost wake-up was reproduced and the workaround checked with
CHECKED_WITH = {"pyzmq": "27.3.0", "jupyter_client": "8.10.0", "nbclient": "0.11.0"}


def rearm_after_send(channel) -> None:
    """Make ``channel`` (a kernel client's asyncio shell channel) re-check its socket after
    every send, so a reply that arrived meanwhile still wakes the coroutine awaiting it."""
    send = channel.send

    def send_and_rearm(msg):
        send(msg)
        channel.socket.get(zmq.EVENTS)

    channel.send = send_and_rearm


class RearmingKernelClient(AsyncKernelClient):
    """jupyter_client's asyncio kernel client whose shell channel re-checks its socket after
    every send (:func:`rearm_after_send`)."""

    @property
    def shell_channel(self):
        channel = super().shell_channel
        if not getattr(channel, "_leglib_rearmed", False):
            rearm_after_send(channel)
            channel._leglib_rearmed = True
        return channel


class RearmingKernelManager(AsyncKernelManager):
    """The kernel manager nbclient is given (``kernel_manager_class``): its clients are
    :class:`RearmingKernelClient`. Papermill's own engine runs the notebooks."""

    client_class = DottedObjectName("leglib.notebook.wakeup.RearmingKernelClient")
    client_factory = Type(RearmingKernelClient, klass=AsyncKernelClient)


class Engine:
    """Papermill's own nbclient engine, its kernel clients re-armed (``papermill --engine leglib``).

    Papermill loads its engines' entry points while it imports its engines module, so this
    one reaches papermill only when a notebook runs."""

    @staticmethod
    def _nbclient():
        from papermill.engines import NBClientEngine  # load time: papermill, imported by papermill itself
        return NBClientEngine

    @classmethod
    def execute_notebook(cls, nb, kernel_name, **kwargs):
        kwargs.setdefault("kernel_manager_class", RearmingKernelManager)
        return cls._nbclient().execute_notebook(nb, kernel_name, **kwargs)

    @classmethod
    def nb_kernel_name(cls, nb, name=None):
        return cls._nbclient().nb_kernel_name(nb, name)

    @classmethod
    def nb_language(cls, nb, language=None):
        return cls._nbclient().nb_language(nb, language)
