"""The workflow side of ``gdt eval``: a copy of a workflow with another fusion policy, and which bundled scene a
workflow's missing inputs come from."""

from __future__ import annotations

from pathlib import Path

from ..plugins import Registry

FUSIONS = ("most_reliable", "keep_unchanged", "keep_reference", "replace_in_view")
SCENE_DIRS = {"paper_test_scene": "paper-test-scene", "fuselage": "fuselage", "test_scene": "test-scene"}


def with_fusion(workflow: str | Path, fusion: str) -> Path:
    """A copy of the workflow, beside it (so its relative paths hold), whose fusion stage is ``fusion`` and whose
    twin goes to ``<twin>_<fusion>``: to compare fusion policies on the same data. The caller deletes it."""
    import yaml

    path = Path(workflow)
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    stages = [s for s in doc.get("stages", []) if s.get("uses") in FUSIONS]
    if not stages:
        raise ValueError(f"{path}: no fusion stage to replace (one of {', '.join(FUSIONS)})")
    for st in stages:
        st["uses"] = fusion
        st.pop("with", None)  # the policies' own parameters differ; the segmentation defaults hold
    doc["twin"] = f"{doc.get('twin', 'twin')}_{fusion}"
    out = path.with_name(f".{path.stem}.{fusion}.yaml")
    out.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return out


def missing_scene(workflow: str | Path, registry: Registry | None = None) -> tuple[str | None, Path] | None:
    """None when the workflow's inputs exist; else (the bundled scene that provides them or None, its directory).

    Reads the YAML directly: loading the workflow would (rightly) reject the missing files."""
    import yaml

    path = Path(workflow)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError):
        return None  # loading the workflow reports it, with the line
    for epoch in doc.get("epochs") or []:
        for inp in (epoch or {}).get("inputs") or []:
            ref = inp.get("path") if isinstance(inp, dict) else inp
            if not isinstance(ref, str):
                continue
            file = Path(ref) if Path(ref).is_absolute() else (path.parent / ref)
            if not file.exists():
                return SCENE_DIRS.get(file.parent.name), file.parent
    return None
