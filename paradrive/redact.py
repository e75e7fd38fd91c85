"""Secrets never reach what a build writes: the ledger, scene logs, markers, index.json, errors.

A secret is a value under a name that looks like one (key, secret, token, password, credential,
session) at any depth: in storage options and the mappings nested in them, in a JSON value
(``client_kwargs={"aws_secret_access_key": "…"}``), in a URL's query (``?X-Amz-Security-Token=…``)
and the environment; and the ``user:password@`` part of a URL. Values are masked where they are
found by name, and again wherever they turn up in free text.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any
from collections.abc import Iterable, Mapping
from urllib.parse import parse_qsl

MASK = "***"
SECRET_NAME = re.compile(r"key|secret|token|passw|credential|session", re.IGNORECASE)
# values shorter than this are not hunted in free text: masking "1" or "s" would garble messages
MIN_SECRET_CHARS = 6
_USERINFO = re.compile(r"(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*://)(?P<user>[^/\s@'\"]+)@")
# name=value in a URL query (or a form body): the value up to the next separator
_QUERY = re.compile(r"(?P<name>[?&;][^=&;#\s'\"]+)=(?P<value>[^&;#\s'\"]*)")
# "name": "value" or 'name': 'value' in JSON or a printed mapping
_QUOTED = re.compile(r"(?P<q>[\"'])(?P<name>[^\"'\n]+)(?P=q)(?P<sep>\s*:\s*)"
                     r"(?P<v>[\"'])(?P<value>(?:(?!(?P=v))[^\n\\]|\\.)*)(?P=v)")


def _is_secret_name(name: object) -> bool:
    return bool(SECRET_NAME.search(str(name)))


def _found_in(value: Any, secret: bool, found: set[str]) -> None:
    """Collect into ``found`` the secrets in ``value``; ``secret``: it sits under a secret name."""
    if isinstance(value, Mapping):
        for name, item in value.items():
            _found_in(item, secret or _is_secret_name(name), found)
    elif isinstance(value, (list, tuple)):
        for item in value:
            _found_in(item, secret, found)
    elif isinstance(value, str):
        if secret:
            found.add(value)
        parsed = _json_container(value)
        if parsed is not None:
            _found_in(parsed, secret, found)
        for match in _USERINFO.finditer(value):
            found.add(match["user"].partition(":")[2])
        query = value.partition("?")[2]
        for name, item in parse_qsl(query.partition("#")[0], keep_blank_values=False):
            if _is_secret_name(name):
                found.add(item)
    elif secret and value is not None and not isinstance(value, bool):
        found.add(str(value))


def _json_container(text: str) -> Any:
    """``text`` parsed when it is a JSON object or array, else None."""
    if not text.lstrip().startswith(("{", "[")):
        return None
    try:
        return json.loads(text)
    except ValueError:
        return None


_REMEMBERED: set[str] = set()


def remember(options: Mapping[str, Any] | None) -> None:
    """Mask the secrets of ``options`` in every later :func:`redact` of this process, also where
    a writer does not have the options at hand (the ledger, a printed error). Each command
    remembers its own options: a later call replaces what an earlier one remembered."""
    _REMEMBERED.clear()
    _found_in(options or {}, False, _REMEMBERED)


def secret_values(options: Mapping[str, Any] | None = None) -> list[str]:
    """The secrets in ``options`` (at any depth), those :func:`remember` was given and the
    environment's, longest first."""
    found: set[str] = set(_REMEMBERED)
    _found_in(options or {}, False, found)
    _found_in(dict(os.environ), False, found)
    return sorted((v for v in found if len(v) >= MIN_SECRET_CHARS), key=len, reverse=True)


def _by_name(text: str) -> str:
    """``text`` with URL credentials, secret query values and quoted secret fields masked."""
    text = _USERINFO.sub(lambda m: f"{m['scheme']}{MASK}@", text)
    text = _QUERY.sub(lambda m: f"{m['name']}={MASK}" if _is_secret_name(m["name"]) else m[0], text)
    return _QUOTED.sub(lambda m: (f"{m['q']}{m['name']}{m['q']}{m['sep']}{m['v']}{MASK}{m['v']}"
                                  if _is_secret_name(m["name"]) else m[0]), text)


def redact(text: object, options: Mapping[str, Any] | None = None) -> str:
    """``text`` with every secret masked: those found by name in the text itself (URL
    credentials and queries, quoted fields) and the values of :func:`secret_values`."""
    out = _by_name(str(text))
    for value in secret_values(options):
        out = out.replace(value, MASK)
    return out


def redact_value(value: Any, secret: bool = False) -> Any:
    """A copy of ``value`` fit to print: under secret names masked at any depth, strings (URLs,
    JSON text) redacted by name."""
    if isinstance(value, Mapping):
        return {name: redact_value(item, secret or _is_secret_name(name)) for name, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [redact_value(item, secret) for item in value]
    if secret and value is not None and not isinstance(value, bool):
        return MASK
    return _by_name(value) if isinstance(value, str) else value


def redact_options(options: Mapping[str, Any]) -> dict:
    """A copy of storage options fit to print: secret-looking values masked at any depth, URLs
    without credentials."""
    return redact_value(options)


def redact_argv(argv: Iterable[str]) -> list[str]:
    """A command line fit to record: the value of ``--storage-option NAME=VALUE`` is masked when
    NAME looks secret, and masked by name inside when it is JSON; every argument then loses URL
    credentials and every secret value the options hold."""
    args = list(argv)
    options: dict[str, Any] = {}
    out: list[str] = []
    option_next = False
    for arg in args:
        flag, eq, rest = arg.partition("=")
        if option_next or (flag == "--storage-option" and eq):
            item = arg if option_next else rest
            item = _option_item(item, options)
            arg = item if option_next else f"{flag}={item}"
        option_next = arg == "--storage-option"
        out.append(arg)
    return [redact(arg, options) for arg in out]


def _option_item(item: str, options: dict[str, Any]) -> str:
    """``NAME=VALUE`` of a storage option with its secrets masked; the option lands in ``options``."""
    name, sep, value = item.partition("=")
    if not sep:
        return item
    parsed = _json_container(value)
    options[name] = parsed if parsed is not None else value
    if _is_secret_name(name):
        return f"{name}={MASK}"
    if parsed is not None:
        return f"{name}={json.dumps(redact_value(parsed), separators=(',', ':'))}"
    return f"{name}={_by_name(value)}"
