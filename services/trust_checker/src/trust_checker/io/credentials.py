"""Reading a transport's password and TLS files, shared by the MQTT and Redis inputs."""

from __future__ import annotations

import os
import ssl
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rap_sdk.errors import ConfigError

__all__ = ["read_credentials"]


def read_credentials(
    what: str, flag: str, config: Any, env: Mapping[str, str] | None = None
) -> tuple[str | None, ssl.SSLContext | None]:
    """The password and TLS context ``config`` names (its ``password_env``,
    ``password_file``, ``secure``, ``ca``, ``cert`` and ``key``; ``what`` names the protocol
    in messages, ``flag`` its command-line prefix), read now (files: call it in a worker
    thread from an event loop); :class:`rap_sdk.ConfigError` saying what is missing."""
    password: str | None = None
    if config.password_env:
        value = (os.environ if env is None else env).get(config.password_env)
        if value is None:
            raise ConfigError(
                f"{what} password: ${config.password_env} is not set - export it before "
                "starting the checker (the password never goes on the command line)"
            )
        password = value
    elif config.password_file:
        try:
            text = Path(config.password_file).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise ConfigError(
                f"{what} password file {config.password_file}: cannot read it ({why}) - give "
                "a readable text file holding the password on its first line"
            ) from None
        password = text.splitlines()[0] if text else ""
        if not password:
            raise ConfigError(
                f"{what} password file {config.password_file}: its first line is empty - "
                "write the password on it"
            )
    context = None
    if config.secure:
        try:
            context = ssl.create_default_context(cafile=config.ca or None)
            if config.cert:
                context.load_cert_chain(config.cert, config.key)
        except OSError as exc:  # ssl.SSLError is one
            hint = f"{flag}-cert/{flag}-key" if config.cert else f"{flag}-ca"
            raise ConfigError(
                f"{what} TLS: cannot load {config.ca or config.cert or 'the CAs'} "
                f"({getattr(exc, 'strerror', None) or exc}) - check {hint}: PEM files, the "
                "key unencrypted and the certificate's"
            ) from None
    return password, context
