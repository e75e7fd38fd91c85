"""Secrets never reach what a build writes: the ledger, scene logs, markers, index.json, errors.

A secret is the value of a storage option or an environment variable whose name looks like one
(key, secret, token, password, credential, session), or the ``user:password@`` part of a URL.
"""

from __future__ import annotations

import os
import re
from typing import Any
from collections.abc import Iterable, Mapping

MASK = "***"
SECRET_NAME = re.compile(r"key|secret|token|passw|credential|session", re.IGNORECASE)
# values shorter than this are not hunted in free text: masking "1" or "s" would garble messages
MIN_SECRET_CHARS = 6
_USERINFO = re.compile(r"(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*://)[^/\s@'\"]+@")


def secret_values(options: Mapping[str, Any] | None = None) -> list[str]:
    """Values under secret-looking names in ``options`` (nested mappings too) and the environment,
    longest first."""
    found: set[str] = set()

    def walk(mapping: Mapping[str, Any]) -> None:
        for name, value in mapping.items():
            if isinstance(value, Mapping):
                walk(value)
            elif SECRET_NAME.search(str(name)) and value is not None and not isinstance(value, bool):
                found.add(str(value))

    walk(options or {})
    walk(os.environ)
    return sorted((v for v in found if len(v) >= MIN_SECRET_CHARS), key=len, reverse=True)


def redact(text: object, options: Mapping[str, Any] | None = None) -> str:
    """``text`` with URL credentials and every secret value (see :func:`secret_values`) masked."""
    out = _USERINFO.sub(lambda m: f"{m['scheme']}{MASK}@", str(text))
    for value in secret_values(options):
        out = out.replace(value, MASK)
    return out


def redact_options(options: Mapping[str, Any]) -> dict:
    """A copy of storage options fit to print: secret-looking values masked, URLs without
    credentials."""
    return {name: (redact_options(value) if isinstance(value, Mapping)
                   else MASK if SECRET_NAME.search(str(name))
                   else redact(value) if isinstance(value, str) else value)
            for name, value in options.items()}


def redact_argv(argv: Iterable[str]) -> list[str]:
    """A command line fit to record: ``--storage-option NAME=VALUE`` with a secret-looking NAME
    keeps NAME only, and every argument loses URL credentials and secret values."""
    out: list[str] = []
    option_next = False
    for arg in argv:
        flag, eq, rest = arg.partition("=")
        if option_next or (flag == "--storage-option" and eq):
            item = arg if option_next else rest
            name, sep, _ = item.partition("=")
            if sep and SECRET_NAME.search(name):
                item = f"{name}={MASK}"
            arg = item if option_next else f"{flag}={item}"
        option_next = arg == "--storage-option"
        out.append(redact(arg))
    return out
