"""MkDocs hook: files of the repository outside ``docs/`` that a page links to (a kept result,
a model's loss curves, a folder's README) are published under ``repo/`` and the links rewritten
to them, so that the site holds what its pages cite. A link to a file that does not exist is
left alone, and the strict build fails on it."""
from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File

LINK = re.compile(r"(\]\()([^)\s#]+)((?:#[^)\s]*)?\))")
PREFIX = "repo"


def _outside_target(page_uri: str, target: str, docs: Path, root: Path) -> Path | None:
    """The repository file a relative link of ``page_uri`` points to, if it is outside docs."""
    if "://" in target or target.startswith(("/", "mailto:")):
        return None
    path = (docs / posixpath.dirname(page_uri) / target).resolve()
    if path.is_relative_to(docs) or not path.is_relative_to(root) or not path.is_file():
        return None
    return path


def _roots(config) -> tuple[Path, Path]:
    docs = Path(config["docs_dir"]).resolve()
    return docs, Path(config["config_file_path"]).resolve().parent


def on_files(files, config):
    """Publish every outside file a page links to as ``repo/<path in the repository>``."""
    docs, root = _roots(config)
    wanted: set[Path] = set()
    for f in files.documentation_pages():
        text = Path(f.abs_src_path).read_text(encoding="utf-8") if f.abs_src_path else ""
        for m in LINK.finditer(text):
            path = _outside_target(f.src_uri, m.group(2), docs, root)
            if path is not None:
                wanted.add(path)
    for path in sorted(wanted):
        uri = f"{PREFIX}/{path.relative_to(root).as_posix()}"
        if files.get_file_from_path(uri) is None:
            files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files


def on_page_markdown(markdown, page, config, files):
    """Point the page's links to outside files at their published copies."""
    docs, root = _roots(config)

    def rewrite(m: re.Match) -> str:
        path = _outside_target(page.file.src_uri, m.group(2), docs, root)
        if path is None:
            return m.group(0)
        uri = f"{PREFIX}/{path.relative_to(root).as_posix()}"
        return m.group(1) + posixpath.relpath(uri, posixpath.dirname(page.file.src_uri) or ".") + m.group(3)

    return LINK.sub(rewrite, markdown)
