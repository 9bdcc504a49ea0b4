"""Self-contained HTML of a report.md (the subset of markdown the reports use; plots embedded)."""

from __future__ import annotations

from pathlib import Path


def _inline(text):
    import html
    import re

    t = html.escape(text, quote=False)
    t = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", t)
    t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
    return re.sub(r"\[([^\]]+)\]\(([^)]+)\)", r'<a href="\2">\1</a>', t)


def _image_tag(alt, src, folder):
    import base64
    import html

    path = Path(folder, src)
    data = base64.b64encode(path.read_bytes()).decode("ascii") if path.is_file() else ""
    return f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}"></figure>'


def markdown_to_html(text: str, folder: str | Path, title: str) -> str:
    """HTML of the markdown subset the reports write (headings, paragraphs, lists, tables,
    images), images embedded as data URIs so the file stands alone. The page records in
    <body data-images-decoded> how many images the browser decoded (checked by a test)."""
    import html
    import re

    body, para, table, items = [], [], [], []

    def flush():
        if para:
            body.append("<p>" + _inline(" ".join(para)) + "</p>")
            para.clear()
        if items:
            body.append("<ul>" + "".join(f"<li>{_inline(x)}</li>" for x in items) + "</ul>")
            items.clear()
        if table:
            head, rows = table[0], table[2:]
            body.append(
                "<table><thead><tr>"
                + "".join(f"<th>{_inline(c)}</th>" for c in head)
                + "</tr></thead><tbody>"
                + "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>" for r in rows)
                + "</tbody></table>"
            )
            table.clear()

    for line in text.splitlines():
        image = re.fullmatch(r"!\[([^\]]*)\]\(([^)]+)\)", line.strip())
        if not line.strip():
            flush()
        elif line.startswith("#"):
            flush()
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{_inline(line[level:].strip())}</h{level}>")
        elif image:
            flush()
            body.append(_image_tag(image.group(1), image.group(2), folder))
        elif line.startswith("|"):
            table.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif line.startswith("- "):
            items.append(line[2:])
        else:
            para.append(line.strip())
    flush()
    style = (
        "body{font-family:sans-serif;max-width:72em;margin:1em auto;padding:0 1em;line-height:1.4}"
        "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:2px 6px;"
        "font-size:0.9em}th{background:#eee}img{max-width:100%}code{background:#f4f4f4}"
    )
    script = (
        "window.addEventListener('load',function(){var n=0;document.querySelectorAll('img').forEach("
        "function(i){if(i.complete&&i.naturalWidth>0)n++});document.body.dataset.imagesDecoded=n;});"
    )
    return (
        '<!DOCTYPE html><html><head><meta charset="utf-8"><title>'
        + html.escape(title)
        + "</title><style>"
        + style
        + "</style><script>"
        + script
        + "</script></head><body>"
        + "\n".join(body)
        + "</body></html>"
    )


def write_html(path: str | Path, markdown_text: str, folder: str | Path, *, title: str) -> Path:
    Path(path).write_text(markdown_to_html(markdown_text, folder, title))
    return Path(path)
