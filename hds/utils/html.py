"""A markdown report as one self-contained HTML page: its tables rendered, its figures embedded
as base64 data (a page that opens anywhere, mailed or moved, with nothing beside it)."""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 72rem; margin: 2rem auto; padding: 0 1rem;
       line-height: 1.45; color: #222; }
table { border-collapse: collapse; margin: 0.8rem 0; font-size: 0.92rem; }
th, td { border: 1px solid #ccc; padding: 0.25rem 0.6rem; text-align: left; }
th { background: #f2f2f2; }
code { background: #f4f4f4; padding: 0 0.2rem; }
img { max-width: 100%; }
blockquote { border-left: 4px solid #e0a000; margin: 0.8rem 0; padding: 0.2rem 0.8rem;
             background: #fff8e6; }
"""

_IMAGE = re.compile(r'<img src="([^"]+)"')


def _embedded(match: re.Match, base: Path) -> str:
    """An <img> whose file (relative to base) is inlined as a data URI; left as it was where
    the source is already data or a URL, or the file is missing."""
    source = html.unescape(match.group(1))
    path = base / source
    if source.startswith(("data:", "http:", "https:")) or not path.is_file():
        return match.group(0)
    kind = {".png": "png", ".gif": "gif", ".jpg": "jpeg", ".jpeg": "jpeg", ".svg": "svg+xml"}
    mime = f"image/{kind.get(path.suffix.lower(), 'png')}"
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img src="data:{mime};base64,{data}"'


def markdown_page(text: str, base: Path, title: str) -> str:
    """The HTML page of markdown `text` (tables included), images relative to `base` inlined."""
    from markdown_it import MarkdownIt  # rich's markdown parser: already installed with it

    body = MarkdownIt("commonmark").enable("table").render(text)
    body = _IMAGE.sub(lambda m: _embedded(m, Path(base)), body)
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{STYLE}</style>\n</head>\n"
        f"<body>\n{body}</body>\n</html>\n"
    )
