"""MkDocs hooks (`hooks:` in mkdocs.yml): the parts of the manual that come from the code, made at build time.

- `openapi.json`, the FastAPI app's own OpenAPI document, is written into the site, and a table of its
  endpoints replaces the marker `<!-- generated: endpoints -->` (the HTTP API page);
- the `--help` epilog of `branchrange record` / `replay` replaces `<!-- generated: exit-codes -->`
  (the troubleshooting page);
- the benchmark logs (`benchmarks/results/*.md`) and the overlays they show become pages of the site
  at the same paths, so the manual links to them as they lie in the repository;
- each figure a page quotes from a benchmark's JSON result file (`<!-- fig FILE PATH FORMAT -->…<!-- /fig -->`,
  `docs_figures.py`) is read from that file; one that cannot be read, or whose typed text differs from the
  file, is a warning, so the strict build fails.

Nothing here downloads anything or needs a camera, a model file or the network.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

from docs_figures import FigureError, drifted, render
from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files
from mkdocs.structure.pages import Page

ROOT = Path(__file__).resolve().parents[1]
#: Files outside docs/ that the site serves at their repository path (globs relative to the repository).
EXTRA_FILES = ("benchmarks/results/*.md", "benchmarks/segmenter_overlays/*.png", "benchmarks/branchnet_training/*/*")
OPENAPI_FILE = "openapi.json"
HTTP_METHODS = ("get", "post", "put", "patch", "delete")
log = logging.getLogger("mkdocs.hooks.docs_figures")


@cache
def openapi_document() -> dict[str, Any]:
    """The OpenAPI document of the full service: the POST routes (an estimator) and the daemon's `/latest`;
    made once per build."""
    from api.app import create_app
    from api.estimator import PipelineEstimator
    from branchrange.config.sections import ApiConfig

    return create_app(ApiConfig(), PipelineEstimator()).openapi()


def _type_of(schema: dict[str, Any]) -> str:
    """A field's type as a reader wants it: `file`, `number`, one of an enum's values; `null` left out."""
    options = [option for option in schema.get("anyOf", [schema]) if option.get("type") != "null"]
    names = []
    for option in options:
        if "enum" in option:
            names.append(" \\| ".join(f"`{value}`" for value in option["enum"]))
        elif option.get("contentMediaType"):
            names.append("file")
        else:
            names.append(str(option.get("type", "")))
    return ", ".join(names)


def form_fields_table(document: dict[str, Any], operation: dict[str, Any]) -> str:
    """A Markdown table of an operation's multipart form fields (name, type, required, description), or ''."""
    body = operation.get("requestBody", {}).get("content", {}).get("multipart/form-data")
    if body is None:
        return ""
    schema = document["components"]["schemas"][body["schema"]["$ref"].rsplit("/", 1)[-1]]
    required = set(schema.get("required", []))
    rows = ["| field | type | required | what it is |", "|---|---|---|---|"]
    for name, field in schema["properties"].items():
        need = "yes" if name in required else ""
        rows.append(f"| `{name}` | {_type_of(field)} | {need} | {field.get('description', '')} |")
    return "\n".join(rows)


def endpoints_table(document: dict[str, Any]) -> str:
    """Markdown of the document's operations: one table of all of them (method, path, summary, documented
    status codes), then each one that takes a form with the table of its fields."""
    rows = ["| method | path | what it does | answers |", "|---|---|---|---|"]
    forms = []
    for path, operations in document["paths"].items():
        for method in HTTP_METHODS:
            operation = operations.get(method)
            if operation is None:
                continue
            summary = operation.get("summary") or operation.get("description", "").split("\n")[0]
            statuses = ", ".join(sorted(operation.get("responses", {})))
            rows.append(f"| `{method.upper()}` | `{path}` | {summary} | {statuses} |")
            fields = form_fields_table(document, operation)
            if fields:
                heading = f"### `{method.upper()} {path}`"
                forms.append(f"{heading}\n\n{summary}. Form fields (multipart/form-data):\n\n{fields}")
    return "\n\n".join(["\n".join(rows), *forms])


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
    """Replace each generation marker in a page by what the code says today, and each figure by its value in
    its result file."""
    for marker, make in GENERATED.items():
        if marker in markdown:
            markdown = markdown.replace(marker, make())
    source = Path(page.file.abs_src_path or page.file.src_uri)
    try:
        for figure, value in drifted(source, markdown):
            log.warning(
                "%s: the page shows %s, %s says %s (python tools/docs_figures.py --write)",
                figure.where(),
                figure.shown,
                figure.file,
                value,
            )
        return render(source, markdown)
    except FigureError as error:
        log.warning("%s", error)
        return markdown
