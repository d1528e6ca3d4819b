"""MkDocs hooks (`hooks:` in mkdocs.yml): the parts of the manual that come from the code, made at build time.

- `openapi.json`, the FastAPI app's own OpenAPI document, is written into the site, and a table of its
  endpoints replaces the marker `<!-- generated: endpoints -->` (the HTTP API page);
- the `--help` epilog of `branchrange record` / `replay` replaces `<!-- generated: exit-codes -->`
  (the troubleshooting page);
- the benchmark logs (`benchmarks/results/*.md`) and the overlays they show become pages of the site
  at the same paths, so the manual links to them as they lie in the repository.

Nothing here downloads anything or needs a camera, a model file or the network.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files
from mkdocs.structure.pages import Page

ROOT = Path(__file__).resolve().parents[1]
#: Files outside docs/ that the site serves at their repository path (globs relative to the repository).
EXTRA_FILES = ("benchmarks/results/*.md", "benchmarks/segmenter_overlays/*.png", "benchmarks/branchnet_training/*/*")
OPENAPI_FILE = "openapi.json"
HTTP_METHODS = ("get", "post", "put", "patch", "delete")


@cache
def openapi_document() -> dict[str, Any]:
    """The OpenAPI document of the full service: the POST routes (an estimator) and the daemon's `/latest`;
    made once per build."""
    from api.app import create_app
    from api.estimator import PipelineEstimator
    from branchrange.core.config import ApiConfig

    return create_app(ApiConfig(), PipelineEstimator()).openapi()


def endpoints_table(document: dict[str, Any]) -> str:
    """A Markdown table of the document's operations: method, path, summary and documented status codes."""
    rows = ["| method | path | what it does | answers |", "|---|---|---|---|"]
    for path, operations in document["paths"].items():
        for method in HTTP_METHODS:
            operation = operations.get(method)
            if operation is None:
                continue
            summary = operation.get("summary") or operation.get("description", "").split("\n")[0]
            statuses = ", ".join(sorted(operation.get("responses", {})))
            rows.append(f"| `{method.upper()}` | `{path}` | {summary} | {statuses} |")
    return "\n".join(rows)


def exit_codes_block() -> str:
    """The exit codes exactly as `branchrange record --help` and `replay --help` print them."""
    from branchrange.commands.exit_codes import EPILOG

    return f"```text\n{EPILOG}\n```"


#: Marker in a page's Markdown → what replaces it.
GENERATED: dict[str, Callable[[], str]] = {
    "<!-- generated: endpoints -->": lambda: endpoints_table(openapi_document()),
    "<!-- generated: exit-codes -->": exit_codes_block,
}


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the benchmark logs, their images and the generated `openapi.json` to the site."""
    for pattern in EXTRA_FILES:
        for path in sorted(ROOT.glob(pattern)):
            files.append(
                File(
                    path.relative_to(ROOT).as_posix(),
                    src_dir=str(ROOT),
                    dest_dir=config.site_dir,
                    use_directory_urls=config.use_directory_urls,
                )
            )
    files.append(File.generated(config, OPENAPI_FILE, content=json.dumps(openapi_document(), indent=2)))
    return files


def on_page_markdown(markdown: str, page: Page, config: MkDocsConfig, files: Files) -> str:
    """Replace each generation marker in a page by what the code says today."""
    for marker, make in GENERATED.items():
        if marker in markdown:
            markdown = markdown.replace(marker, make())
    return markdown
