"""The lost wake-up of the Jupyter client stack that hung notebook runs (nbclient#312,
jupyter_client#1059): reproduced here at the versions leglib.notebook.wakeup was checked
with, and the workaround shown to take the reply at once. When an upgrade fixes it upstream,
the reproduction fails: then the workaround can go."""

import asyncio
import time
from importlib import metadata

import pytest
import zmq
import zmq.asyncio
from jupyter_client.channels import AsyncZMQSocketChannel
from jupyter_client.session import Session

from leglib.notebook.wakeup import CHECKED_WITH, RearmingKernelManager, rearm_after_send


def test_the_versions_are_the_ones_the_workaround_was_checked_with():
    assert {name: metadata.version(name) for name in CHECKED_WITH} == CHECKED_WITH


async def _reply_wait(rearm: bool) -> float:
    """An execute_reply comes in, then the client sends on the shell (the Output widget's
    sync) before its loop ran: how long the awaited poll takes to see the reply [s]."""
    actx, ctx = zmq.asyncio.Context(), zmq.Context()
    client = actx.socket(zmq.DEALER)
    port = client.bind_to_random_port("tcp://127.0.0.1")
    kernel = ctx.socket(zmq.ROUTER)
    kernel.connect(f"tcp://127.0.0.1:{port}")
    session = Session(key=b"")
    channel = AsyncZMQSocketChannel(client, session)
    if rearm:
        rearm_after_send(channel)
    try:
        channel.send(session.msg("execute_request", content={}))
        ident, *_ = kernel.recv_multipart()
        waiting = asyncio.ensure_future(channel.get_msg(timeout=3.0))
        await asyncio.sleep(0.05)          # the poll is registered
        session.send(kernel, "execute_reply", content={}, ident=ident)
        time.sleep(0.2)                    # the reply is in before the loop runs again
        channel.send(session.msg("comm_msg", content={}))
        t0 = time.monotonic()
        msg = await waiting
        assert msg["header"]["msg_type"] == "execute_reply"
        return time.monotonic() - t0
    finally:
        client.close(0)
        kernel.close(0)
        ctx.term()


@pytest.mark.slow
def test_a_send_on_the_shell_swallows_the_wakeup_of_a_reply_unless_rearmed():
    assert asyncio.run(_reply_wait(rearm=False)) > 2.0   # the bug: woken only by the poll's timeout
    assert asyncio.run(_reply_wait(rearm=True)) < 1.0


def test_the_kernel_manager_gives_rearmed_clients():
    km = RearmingKernelManager()
    kc = km.client()
    try:
        assert getattr(kc.shell_channel, "_leglib_rearmed", False)
    finally:
        kc.stop_channels()


def test_papermills_command_line_finds_the_engine():
    from papermill.engines import papermill_engines

    from leglib.notebook.wakeup import Engine
    assert papermill_engines.get_engine("leglib") is Engine
