"""A bridge's password and TLS context, read when its link connects (any protocol).

The spec names where the secrets are (``password_env``, ``password_file``, ``ca``,
``cert``, ``key``), never the secrets themselves. :func:`link_credentials` reads them
anew at each connection, so that a rotated password or certificate is taken at the next
reconnect. It reads files: call it in a worker thread (``anyio.to_thread.run_sync``).
"""

from __future__ import annotations

import os
import ssl
from pathlib import Path

from .core import LinkDown
from .spec import BridgeSpec

__all__ = ["link_credentials"]


def link_credentials(spec: BridgeSpec, what: str) -> tuple[str | None, ssl.SSLContext | None]:
    """The password and TLS context ``spec`` names (None, None: neither), read now;
    :class:`LinkDown` saying what to fix otherwise. ``what`` names the protocol in the
    messages (``MQTT``, ``Redis``)."""
    password: str | None = None
    if spec.password_env:
        password = os.environ.get(spec.password_env)
        if password is None:
            raise LinkDown(
                f"{what} password: ${spec.password_env} is not set",
                f"export {spec.password_env} before starting the bridge",
            )
    elif spec.password_file:
        try:
            text = Path(spec.password_file).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise LinkDown(
                f"{what} password file {spec.password_file}: cannot read it ({why})",
                "give a readable text file holding the password on its first line",
            ) from None
        password = text.splitlines()[0] if text else ""
        if not password:
            raise LinkDown(
                f"{what} password file {spec.password_file}: its first line is empty",
                "write the password on it",
            )
    context = None
    if spec.tls:
        try:
            context = ssl.create_default_context(cafile=spec.ca or None)
            if spec.cert:
                context.load_cert_chain(spec.cert, spec.key)
        except OSError as exc:  # ssl.SSLError is one
            raise LinkDown(
                f"{what} TLS: cannot load {spec.ca or spec.cert or 'the CAs'} "
                f"({getattr(exc, 'strerror', None) or exc})",
                "check ca, cert and key: PEM files, the key unencrypted",
            ) from None
    return password, context
