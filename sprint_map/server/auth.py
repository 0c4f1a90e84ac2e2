"""Bearer-token authentication and the rule that keeps an unauthenticated server on loopback."""

from __future__ import annotations

import hmac
import ipaddress
import os
from pathlib import Path

from sprint_map.errors import InputError, UnsafeServeError
from sprint_map.server.config import ServerConfig
from sprint_map.util.validation import decode_text

__all__ = ["LOOPBACK_NAMES", "check_bind", "is_loopback", "load_token", "served_hosts",
           "token_matches"]


def load_token(config: ServerConfig) -> str | None:
    """The configured bearer token: ``config.token_file`` if set, else ``$token_env``, else None.

    Raises
    ------
    InputError
        If the token file cannot be read, is empty, or it or ``$token_env`` is not UTF-8 text.
    """
    if config.token_file:
        try:
            raw = Path(config.token_file).read_bytes()
        except OSError as exc:
            raise InputError(f"cannot read token file {config.token_file}: "
                             f"{exc.strerror or exc}") from exc
        token = decode_text(raw, f"token file {config.token_file}", secret=True).strip()
        if not token:
            raise InputError(f"token file {config.token_file} is empty")
        return token
    token = decode_text(os.environ.get(config.token_env, ""), f"${config.token_env}",
                        secret=True).strip()
    return token or None


def is_loopback(host: str) -> bool:
    """Whether ``host`` only accepts connections from this machine (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to anything


#: Host names of this machine a tokenless server always answers.
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "[::1]"})


def served_hosts(host: str, token: str | None, extra: tuple[str, ...] = ()
                 ) -> frozenset[str] | None:
    """The ``Host`` names a server bound to ``host`` answers: without a token its address,
    the loopback names and ``extra`` (DNS rebinding: a page's own name is refused); with a
    token, None (any: the token is the check)."""
    if token is not None:
        return None
    bound = host.strip().lower()
    bound = f"[{bound.strip('[]')}]" if ":" in bound else bound
    return LOOPBACK_NAMES | {bound} | {name.strip().lower() for name in extra}


def check_bind(host: str, token: str | None) -> None:
    """Refuse to listen beyond loopback without a token.

    Raises
    ------
    UnsafeServeError
        ``host`` is not loopback and no token is configured.
    """
    if token is None and not is_loopback(host):
        raise UnsafeServeError(
            f"refusing to listen on {host} without a bearer token: set $SPRINT_MAP_TOKEN or "
            "--token-file, or listen on 127.0.0.1"
        )


def token_matches(header: str | None, token: str) -> bool:
    """Whether an ``Authorization`` header carries ``Bearer <token>`` (constant-time compare)."""
    if not header:
        return False
    scheme, _, value = header.partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(value.strip().encode(),
                                                              token.encode())
