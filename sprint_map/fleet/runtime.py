"""Connecting to Ray from a ``--ray`` value: ``local``, ``auto`` or a cluster address.

``local`` starts a private runtime on this machine (``ray.init()`` with this machine's cores);
``auto`` joins the cluster this machine is part of (``ray start`` ran here: ``RAY_ADDRESS`` or
the local head's address file); any other value is a cluster address (``ray://host:10001`` for
Ray Client, or ``host:6379``). Ray is imported here, on first use only.
"""

from __future__ import annotations

import os
from typing import Any

from sprint_map.errors import InputError

__all__ = ["RAY_HELP", "connect", "require_ray"]

RAY_HELP = ("run on Ray: 'local' (a private runtime on this machine), 'auto' (the cluster this "
            "machine joined with `ray start`) or a cluster ADDRESS; needs pip install "
            "'sprint-map[ray]'")


def require_ray() -> Any:
    """The ``ray`` module, or an :class:`InputError` saying how to install it."""
    try:
        import ray
    except ImportError as exc:  # the optional extra is not installed
        raise InputError("--ray needs Ray: pip install 'sprint-map[ray]' "
                         f"(or pip install ray) ({exc})") from exc
    return ray


def connect(spec: str, *, num_cpus: int | None = None) -> Any:
    """Connect this process to Ray as ``spec`` says; returns the ``ray`` module.

    Already connected (a test's runtime, or a second call): the running runtime is used as it
    is. ``num_cpus`` caps a ``local`` runtime (default: this machine's cores).

    Notes
    -----
    Starting a local runtime takes a few seconds (~4.6 s on the 2-core test machine under
    load); joining a running cluster well under one.
    """
    if not spec or spec.strip() != spec:
        raise InputError(f"--ray {spec!r}: give local, auto or a cluster address")
    ray = require_ray()
    if ray.is_initialized():
        return ray
    common: dict[str, Any] = {"log_to_driver": False, "configure_logging": True,
                              "logging_level": "ERROR"}
    if spec == "local":  # always a new runtime, even beside a cluster running here
        ray.init(address="local", num_cpus=num_cpus or os.cpu_count() or 1,
                 include_dashboard=False, **common)
    else:
        try:
            ray.init(address=spec, **common)
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise InputError(f"--ray {spec}: cannot join the Ray cluster ({exc})") from exc
    return ray
