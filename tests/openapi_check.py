"""Check a real HTTP response against the OpenAPI document the server itself serves.

For `method path → status`: the status must be documented for that operation, the response's
media type must be one the document lists for it, a JSON body must validate against the
documented schema (JSON Schema 2020-12, which OpenAPI 3.1 uses; `$ref`s resolve inside the
document's `components`), and documented headers must be present.
"""

from __future__ import annotations

import jsonschema


def check_response(spec: dict, method: str, path: str, response) -> None:
    """Raise AssertionError naming the mismatch between `response` (an httpx response) and `spec`."""
    assert path in spec["paths"], f"{path} is not in the served OpenAPI document"
    operation = spec["paths"][path][method.lower()]
    where = f"{method.upper()} {path} → {response.status_code}"
    documented = operation["responses"].get(str(response.status_code))
    assert documented is not None, f"{where}: status not documented (documented: {sorted(operation['responses'])})"
    content = documented.get("content", {})
    media = response.headers.get("content-type", "").split(";")[0].strip()
    assert media in content, f"{where}: content type {media!r} not documented (documented: {sorted(content)})"
    for header in documented.get("headers", {}):
        assert header.lower() in response.headers, f"{where}: documented header {header} missing"
    schema = content[media].get("schema")
    if media == "application/json" and schema:
        document = {**schema, "components": spec["components"]}
        errors = sorted(jsonschema.Draft202012Validator(document).iter_errors(response.json()), key=str)
        assert not errors, (
            f"{where}: body does not match the documented schema: {errors[0].message} at {list(errors[0].path)}"
        )
