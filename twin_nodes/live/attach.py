"""A Foxglove server beside another command (``compare``, ``monitor``, ``bridge``): ``--foxglove [PORT]``.

Two calls wire it into a command's module::

    from twin_nodes.live.attach import add_foxglove_option, foxglove_beside

    add_foxglove_option(parser)                      # --foxglove [PORT] (8765 when given bare)
    with foxglove_beside(args.foxglove, domain_id):  # no-op when args.foxglove is None
        ...run the command...

The server is its own process (:mod:`twin_nodes.live.foxglove_node`) on the command's ROS domain,
started before the command's work so that it sees every topic, and stopped (SIGINT) after it.
A command that picks its domain itself (``compare`` without ``--domain-id``) takes one first with
:func:`free_domain` and passes it on, so both run on the same one.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator

from twin_nodes.base.errors import TwinError

__all__ = ["add_foxglove_option", "foxglove_beside", "free_domain", "DEFAULT_PORT"]

DEFAULT_PORT = 8765


def add_foxglove_option(parser: argparse.ArgumentParser, port_type: Any = int) -> None:
    """``--foxglove [PORT]``; the CLI passes ``port_type=twin_nodes.cli.options.port()`` (range-checked)."""
    parser.add_argument("--foxglove", nargs="?", type=port_type, const=DEFAULT_PORT, default=None, metavar="PORT",
                        help=f"also serve the graph's topics to Foxglove on ws://127.0.0.1:PORT "
                             f"(default {DEFAULT_PORT}; layout: layouts/rotortwin.json)")


def free_domain() -> int:
    """A ROS domain id nobody uses now (leased and released at once, so the command leases it next)."""
    from twin_nodes.graph.domains import lease_domain

    with lease_domain() as lease:
        return lease.domain_id


@contextlib.contextmanager
def foxglove_beside(port: int | None, domain_id: int | None = None, *, host: str = "127.0.0.1",
                    mcap: str | None = None, timeout_s: float = 60.0) -> Iterator[str | None]:
    """Run the Foxglove server for the duration of the ``with`` block; yields its ``ws://`` URL
    (None when ``port`` is None: nothing is started)."""
    if port is None:
        yield None
        return
    from twin_nodes.graph.orchestrator import _die_with_parent, ros_env
    from twin_nodes.live.layout import LAYOUT_PATH
    from twin_nodes.live.shadow import module_command

    # a given domain: the graph's environment (localhost discovery); else exactly the caller's
    env = ros_env(domain_id) if domain_id is not None else {**os.environ, "PYTHONUNBUFFERED": "1"}
    params = {"port": int(port), "host": host}
    if mcap:
        params["mcap"] = str(mcap)
    log = tempfile.NamedTemporaryFile("w+", prefix="rotortwin_foxglove_", suffix=".log", delete=False)
    p = subprocess.Popen(module_command("twin_nodes.live.foxglove_node", [], params), env=env,
                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log, text=True,
                         start_new_session=True, preexec_fn=_die_with_parent())
    url: list[str] = []

    def reader() -> None:
        assert p.stdout is not None
        for line in p.stdout:
            if line.startswith("FOXGLOVE ") and not url:
                url.append(line.split()[1])

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        t_end = threading.Event()
        waited = 0.0
        while not url and p.poll() is None and waited < timeout_s:
            t_end.wait(0.1)
            waited += 0.1
        if not url:
            log.seek(0)
            tail = "\n".join(log.read().splitlines()[-5:])
            raise TwinError(f"--foxglove: the Foxglove server did not start on port {port}:\n{tail}")
        print(f"rotortwin: Foxglove: open {url[0]} (layout {LAYOUT_PATH})", file=sys.stderr, flush=True)
        yield url[0]
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        log.close()
        Path(log.name).unlink(missing_ok=True)
