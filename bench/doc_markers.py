"""The one way the benchmark scripts write a generated block into a doc: the text between
``<!-- NAME -->`` and ``<!-- /NAME -->`` replaced, the doc written atomically (figures in docs are
generated, not typed). Imported as ``bench.doc_markers`` with the repository on ``sys.path``."""

from __future__ import annotations

from pathlib import Path

from geocues.atomic import atomic_path


def replace_block(doc: Path, marker: str, text: str) -> None:
    """Put ``text`` between the ``marker`` markers of ``doc``; SystemExit naming them when absent."""
    start, end = f"<!-- {marker} -->", f"<!-- /{marker} -->"
    body = Path(doc).read_text()
    if start not in body or end not in body:
        raise SystemExit(f"{doc} has no {start} ... {end} markers")
    head, rest = body.split(start, 1)
    tail = rest.split(end, 1)[1]
    with atomic_path(doc) as tmp:
        tmp.write_text(f"{head}{start}\n{text.rstrip()}\n{end}{tail}")
