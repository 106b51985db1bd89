"""The HTML page a browser gets for a directory without an ``index.html``, and the URL of a
content path that it and the gateway's headers share.

Every name comes from a stranger's DAG: it is escaped for HTML and percent-encoded in links,
so a name cannot inject markup or point a link elsewhere than its own entry.
"""

from __future__ import annotations

from html import escape
from urllib.parse import quote

from robocloud.cid import CID
from robocloud.dagpb import Link


def content_url(root: CID, path: list[str]) -> str:
    """``/ipfs/{root}/{path}`` with each segment percent-encoded, for headers and links.

    Names are any UTF-8 and may hold ``?``, ``#``, ``%`` or CR/LF: decoded, they broke the
    ``Location`` of the ``index.html`` redirect and made ``X-Ipfs-Path`` a 500 (headers are
    Latin-1). Kubo sends the decoded path's UTF-8 bytes as they are; the encoded path is the
    same path, and safe in any header and any URL.
    """
    return "/".join(["", "ipfs", str(root), *(quote(segment, safe="") for segment in path)])


def directory_page(root: CID, path: list[str], directory: CID, entries: list[Link]) -> str:
    """A listing of ``entries``: name (linked by path), cumulative size, CID (linked by CID)."""
    base = content_url(root, path)
    title = escape("/".join(["", "ipfs", str(root), *path]))
    rows = []
    if path:
        parent = base.rsplit("/", 1)[0] + "/"
        rows.append(f'<tr><td><a href="{escape(parent)}">..</a></td><td></td><td></td></tr>')
    for entry in sorted(entries, key=lambda link: link.name.encode()):
        href = escape(f"{base}/{quote(entry.name, safe='')}")
        rows.append(
            f'<tr><td><a href="{href}">{escape(entry.name)}</a></td>'
            f"<td>{entry.tsize}</td>"
            f'<td><a href="/ipfs/{entry.cid}">{entry.cid}</a></td></tr>'
        )
    return (
        "<!DOCTYPE html>\n"
        f'<html><head><meta charset="utf-8"><title>{title}</title></head><body>\n'
        f"<h1>Index of {title}</h1>\n<p>{directory}</p>\n"
        "<table><thead><tr><th>name</th><th>size (DAG)</th><th>CID</th></tr></thead><tbody>\n"
        + "\n".join(rows)
        + "\n</tbody></table></body></html>\n"
    )
