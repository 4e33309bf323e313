"""Content negotiation: which of the media types a route offers the Accept header prefers."""

from __future__ import annotations


def negotiate(accept: str | None, offered: list[str]) -> str | None:
    """The offered media type the Accept header prefers (q-values, type/* and */*; ties go to
    the earlier offer), or None when it accepts none of them."""
    if not accept:
        return offered[0]
    prefs = []
    for entry in accept.split(","):
        kind, *params = (p.strip() for p in entry.split(";"))
        q = 1.0
        for p in params:
            if p.startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        prefs.append((kind.lower(), q))
    best, best_q = None, 0.0
    for media in offered:
        q = max((q for kind, q in prefs if kind in (media, media.split("/")[0] + "/*", "*/*")), default=0.0)
        if q > best_q:
            best, best_q = media, q
    return best
