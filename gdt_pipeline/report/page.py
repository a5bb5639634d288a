"""The report page: one HTML file with plotly.js, its licence, the CSS, the figures' data and the script inlined, so
that nothing is fetched when it is opened (offline, from a file:// URL, or mailed on)."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import GdtError
from ..export_values import written_in_place
from .figures import SOLID, STYLE, state_name, state_rgb
from .tables import esc

TYPED_ARRAYS_SINCE = (2, 28, 0)  # first plotly.js that reads {"dtype", "bdata"} typed arrays


@dataclass(frozen=True)
class PlotlyAsset:
    """The installed plotly.js bundle: its file, version and the licence text of the distribution it came with."""

    path: Path
    version: tuple[int, int, int]
    licence: str

    @property
    def typed_arrays(self) -> bool:
        """Whether this plotly.js reads typed arrays."""
        return self.version >= TYPED_ARRAYS_SINCE


def plotly_asset() -> PlotlyAsset:
    """plotly.js from the installed plotly package (found without importing it), with its version and licence."""
    spec = importlib.util.find_spec("plotly")
    if spec is None or not spec.submodule_search_locations:
        raise GdtError("gdt report needs the plotly package for its plotly.js: pip install 'plotly>=5.20'")
    path = Path(next(iter(spec.submodule_search_locations))) / "package_data" / "plotly.min.js"
    if not path.is_file():
        raise GdtError(f"the installed plotly package has no {path.name} (looked in {path.parent}); reinstall plotly")
    with open(path, encoding="utf-8") as fh:
        head = fh.read(400)
    found = re.search(r"plotly\.js v(\d+)\.(\d+)\.(\d+)", head)
    version = tuple(int(g) for g in found.groups()) if found else (0, 0, 0)
    licence = "plotly.js is released under the MIT license (licence file not found in the plotly distribution)."
    try:
        dist = importlib.metadata.distribution("plotly")
        files = [f for f in dist.files or [] if f.name.upper().startswith(("LICENSE", "LICENCE"))]
        if files:
            licence = files[0].read_text(encoding="utf-8")
    except importlib.metadata.PackageNotFoundError:
        pass
    return PlotlyAsset(path, version, licence)  # type: ignore[arg-type]


def plain_arrays(value: Any) -> Any:
    """The figures with typed arrays written out as numbers of 7 significant digits (float32's precision), for a
    plotly.js older than 2.28."""
    if isinstance(value, dict):
        if set(value) == {"dtype", "bdata"}:
            import base64

            arr = np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"]).newbyteorder("<"))
            return [float(f"{v:.7g}") for v in arr.tolist()] if arr.dtype.kind == "f" else arr.tolist()
        return {k: plain_arrays(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain_arrays(v) for v in value]
    return value


def _script_safe(path: Path, block: int = 1 << 20) -> Iterator[str]:
    """A script file's text in blocks, with every "</script" (which would end the element early) escaped; the
    file (plotly.js: 4-5 MB) is never held whole."""
    tag, escaped = "</script", "<\\/script"
    carry = ""
    with open(path, encoding="utf-8") as fh:
        while text := fh.read(block):
            text = (carry + text).replace(tag, escaped)
            carry, text = text[-(len(tag) - 1):], text[:-(len(tag) - 1)]  # a tag may straddle two blocks
            yield text
    yield carry.replace(tag, escaped)


def _asset_text(name: str) -> str:
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def toggles_html(layers: list[tuple[int, str]], epochs: list[str]) -> str:
    """Check boxes per change state and per source epoch present in the view, and the whole-twin button."""
    states = sorted({s for s, _ in layers})
    used = [e for e in epochs if any(e == le for _, le in layers)]
    state_boxes = "".join(
        f'<label><input type="checkbox" data-toggle="state" value="{esc(state_name(s))}" checked>'
        f'<span class="swatch" style="background:{state_rgb(s)}"></span>{esc(state_name(s).replace("_", " "))} '
        f'({esc(STYLE.get(s, SOLID)[2])})</label>'
        for s in states)
    epoch_boxes = "".join(f'<label><input type="checkbox" data-toggle="epoch" value="{esc(e)}" checked>{esc(e)}'
                          f'</label>' for e in used)
    return (f'<div class="toggles"><fieldset><legend>change state</legend>{state_boxes}</fieldset>'
            f'<fieldset><legend>supplied by epoch</legend>{epoch_boxes}</fieldset>'
            f'<button id="home" type="button">Whole twin</button></div>')


@dataclass
class PageParts:
    """What the page is made of: HTML fragments in order, and the data its script draws."""

    title: str
    header: str
    sections: list[str]
    data: dict[str, Any]
    footer: str


def _chunks(parts: PageParts, asset: PlotlyAsset) -> Iterator[str]:
    licence = asset.licence.replace("--", "- -")  # "--" may not appear inside an HTML comment
    version = ".".join(map(str, asset.version))
    yield (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
           f'<meta name="viewport" content="width=device-width, initial-scale=1">\n<title>{esc(parts.title)}</title>\n'
           f"<style>\n{_asset_text('page.css')}</style>\n"
           f"<!--\nplotly.js v{version}, embedded from the installed plotly package "
           f"(plotly/package_data/plotly.min.js). Its licence:\n\n{licence}\n-->\n<script>\n")
    yield from _script_safe(asset.path)
    yield f"\n</script>\n</head>\n<body>\n{parts.header}\n"
    yield from (f"{s}\n" for s in parts.sections)
    data = parts.data if asset.typed_arrays else plain_arrays(parts.data)
    yield f'<footer>{parts.footer}</footer>\n<script type="application/json" id="gdt-data">'
    encoder = json.JSONEncoder(separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    for piece in encoder.iterencode(data):  # piece by piece: the page's data is never one more string in memory
        yield piece.replace("</", "<\\/")
    yield f"</script>\n<script>\n{_asset_text('page.js')}</script>\n</body>\n</html>\n"


def write_page(out: Path, parts: PageParts, asset: PlotlyAsset) -> int:
    """Write the page to ``out`` (through a temp file, renamed when complete); return its size in bytes."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with written_in_place(out) as partial, open(partial, "w", encoding="utf-8", newline="\n") as fh:
        for chunk in _chunks(parts, asset):
            fh.write(chunk)
    return out.stat().st_size
