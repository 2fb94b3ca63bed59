"""Showing an archive url: one function, and never its password.

Every place that shows the archive's url (the CLI's lines and JSON, an outbox file's reason, the
console's banner and log, an error) goes through :func:`mask_url`, and every free text that may
carry one (a driver's error, a reason) through :func:`scrub`. A password may sit in the user info
(``user:pw@host``, also with an unescaped ``@`` inside it: ``user:p@ss@host``) or in the query
(libpq's ``?password=``, ``sslpassword=``): both are shown as ``***``.
"""
from __future__ import annotations

import re
from urllib.parse import unquote

MASK = "***"
_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*://)(.*)$", re.S)
#: query keys whose value is a secret (libpq: password, sslpassword)
_SECRET_KEY = re.compile(r"(?i)((?:^|[?&;])[A-Za-z_]*(?:password|secret|token)=)([^&;#\s]*)")
#: a url in free text: scheme://...@ up to a blank or a quote
_URL_IN_TEXT = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^\s'\"<>]+")


def _split(body: str) -> tuple[str | None, str]:
    """(user info, the rest) of a url's body after ``scheme://``; user info None when there is none.

    The user info ends at the last '@' that is not inside the query (a password may hold an '@')."""
    at = body.rfind("@")
    if at < 0:
        return None, body
    q = body.find("?")
    if 0 <= q < at and "=" in body[q:at]:  # that '@' is a query value's: look before the query
        at = body.rfind("@", 0, q)
        if at < 0:
            return None, body
    return body[:at], body[at + 1:]


def secrets_of(url: str | None) -> list[str]:
    """The passwords a url carries (as written and decoded), longest first: what :func:`scrub` removes."""
    if not url:
        return []
    m = _SCHEME.match(str(url))
    if not m:
        return []
    info, rest = _split(m.group(2))
    found = []
    if info is not None and ":" in info:
        found.append(info.split(":", 1)[1])
    found += [v for _, v in _SECRET_KEY.findall(rest)]
    out = set()
    for s in found:
        if s:
            out |= {s, unquote(s)}
    return sorted((s for s in out if len(s) >= 3 or s in found), key=len, reverse=True)


def mask_url(url: str | None) -> str:
    """``url`` with any password shown as ``***`` (user info and query); a text that is no url is returned as is."""
    if not url:
        return ""
    s = str(url)
    m = _SCHEME.match(s)
    if not m:
        return s
    scheme, body = m.groups()
    info, rest = _split(body)
    rest = _SECRET_KEY.sub(lambda k: k.group(1) + MASK, rest)
    if info is None:
        return scheme + rest
    if ":" in info:
        info = info.split(":", 1)[0] + ":" + MASK
    return f"{scheme}{info}@{rest}"


def scrub(text, url: str | None = None) -> str:
    """``text`` (an error, a reason) with every password of ``url`` and of any url in it masked."""
    t = _URL_IN_TEXT.sub(lambda m: mask_url(m.group(0)), str(text))
    for s in secrets_of(url):
        t = t.replace(s, MASK)
    return _SECRET_KEY.sub(lambda k: k.group(1) + MASK, t) if "=" in t else t
