"""Step 7: the filter stack (add / remove, in order) with a before/after preview of the first frame."""

from __future__ import annotations

import re

import cv2
import numpy as np
from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Horizontal
from textual.widgets import Input, Label, OptionList, Select, Static

from fieldtool.errors import FieldToolError, ParameterError
from fieldtool.processing.filters import FILTERS, FilterStack, preview
from fieldtool.project.model import atomic_write_bytes
from fieldtool.run.geometry import roi_and_mask
from fieldtool.tui import keys
from fieldtool.tui.fields import DECIMAL_HINT, fmt_num
from fieldtool.tui.screens.base import StepScreen, fieldtool_app
from fieldtool.tui.screens.preview import PNG, PreviewScreen
from fieldtool.tui.widgets.plots import GrayImage


def parse_params(text: str, name: str) -> dict:
    """ "clip_limit=2, tile_grid=8" -> {"name": name, "clip_limit": 2, "tile_grid": 8}."""
    item: dict = {"name": name}
    for part in (p.strip() for p in text.replace(";", ",").split(",")):
        if not part:
            continue
        if "=" not in part:
            hint = f"; {DECIMAL_HINT}" if re.search(r"=\s*[+-]?\d+,\d", text) else ""
            raise ParameterError(f"filter parameters: {part!r} is not 'name=value' (e.g. clip_limit=40){hint}")
        k, v = (s.strip() for s in part.split("=", 1))
        try:
            val: object = int(v)
        except ValueError:
            try:
                val = float(v)
            except ValueError:
                val = v
        item[k] = val
    return item


def example_params(cls) -> str:
    """The parameters input's placeholder: the chosen filter's own parameters with their defaults, so an
    example never disagrees with the default beside it (``clahe``: "defaults: clip_limit=40, tile_grid=8")."""
    shown = [
        f"{p.name}={fmt_num(p.default) if not isinstance(p.default, str) else p.default}"
        for p in cls.params
        if p.default is not None
    ]
    return "defaults: " + ", ".join(shown) if shown else "no parameters to set" if not cls.params else "defaults"


def describe(item: dict) -> str:
    args = ", ".join(f"{k}={fmt_num(v) if isinstance(v, (int, float)) else v}" for k, v in item.items() if k != "name")
    return f"{item['name']}" + (f"  {args}" if args else "  (defaults)")


class FiltersScreen(StepScreen):
    STEP = "filters"
    INTRO = "image enhancement before PIV (optional)"
    BINDINGS = [*keys.FILTERS, keys.run("Preview")]

    def compose_top(self) -> ComposeResult:
        yield OptionList(id="stack")
        with Horizontal(classes="field-line"):
            yield Label("Filter", classes="field-label")
            yield Select(
                [(n, n) for n in FILTERS],
                value="clahe",
                allow_blank=False,
                compact=True,
                id="filter-name",
                type_to_search=False,
            )
        with Horizontal(classes="field-line"):
            yield Label("Parameters", classes="field-label")
            yield Input(placeholder=example_params(FILTERS["clahe"]), compact=True, id="filter-params")
        yield Static("", id="filter-doc")

    def compose_extra(self) -> ComposeResult:
        with Horizontal(id="preview"):
            yield GrayImage(id="before")
            yield GrayImage(id="after")

    def on_mount(self) -> None:
        super().on_mount()
        self.show_doc()

    def focus_first(self) -> None:
        self.query_one("#filter-name", Select).focus()

    def refresh_view(self) -> None:
        lst = self.query_one("#stack", OptionList)
        lst.clear_options()
        items = self.project.filters
        if items:
            lst.add_options([Text(f"{i + 1}. {describe(it)}") for i, it in enumerate(items)])
        else:
            lst.add_option("no filter: frames go to PIV as they are")

    def show_doc(self) -> None:
        name = self.query_one("#filter-name", Select).value
        assert isinstance(name, str)  # the Select has allow_blank=False: always a filter name
        cls = FILTERS[name]
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        parts = []
        for p in cls.params:
            d = (
                "from the image"
                if p.default is None
                else fmt_num(p.default)
                if not isinstance(p.default, str)
                else p.default
            )
            parts.append(f"{p.name} ({p.doc or p.kind.__name__}; default {d})")
        self.query_one("#filter-doc", Static).update(Text(f"{doc}\n" + "; ".join(parts), style="dim"))
        self.query_one("#filter-params", Input).placeholder = example_params(cls)
        self.query_one("#help", Static).update(
            Text(
                "ctrl+t adds the chosen filter with these parameters (empty = defaults); ctrl+y removes the last; "
                "ctrl+r previews"
            )
        )

    def on_select_changed(self, event: Select.Changed) -> None:
        if event.select.id == "filter-name":
            event.stop()
            self.show_doc()

    # -- stack editing -------------------------------------------------------------------------
    def action_add_filter(self) -> None:
        name = self.query_one("#filter-name", Select).value
        assert isinstance(name, str)  # the Select has allow_blank=False: always a filter name
        text = self.query_one("#filter-params", Input).value
        try:
            item = parse_params(text, name)
            new = [*self.project.filters, item]
            FilterStack.from_config(new)
        except FieldToolError as e:
            self.show_errors([str(e)])
            return
        self.project.filters = new
        self.changed()
        self.query_one("#filter-params", Input).value = ""

    def action_remove_filter(self) -> None:
        if not self.project.filters:
            self.notify("the stack is empty")
            return
        self.project.filters = self.project.filters[:-1]
        self.changed()

    def changed(self) -> None:
        fieldtool_app(self).save_project()
        self.show_errors([])
        self.refresh_view()
        self.refresh_marks()

    # -- preview ---------------------------------------------------------------------------------
    def action_run(self) -> None:
        """Filter the first frame: small before/after here, large in a preview screen, and the
        filtered frame written to out/filter_preview.png for the viewer."""
        try:
            inputs = self.session.inputs()
            gray = self.first_gray(inputs)
            roi = self.roi(inputs)
            frames = None
            if FilterStack.from_config(self.project.filters).needs_prepass:
                frames = (self.lens(inputs, f.image) for f in inputs.source)
            # as the pipeline: filtered inside the ROI only (image-based defaults come from the ROI)
            filtered = preview(self.project.filters, gray, frames, roi)
        except FieldToolError as e:
            self.show_errors([str(e)])
            return
        after = self.crop(filtered, roi)
        before = self.crop(gray, roi)
        captions = (f"first frame, std {before.std():.1f}", f"filtered, std {after.std():.1f}")
        self.query_one("#before", GrayImage).set_image(before, captions[0])
        self.query_one("#after", GrayImage).set_image(after, captions[1])
        png = f"{self.session.out_dir.name}/{PNG}"
        try:
            self.session.out_dir.mkdir(parents=True, exist_ok=True)
            ok, buf = cv2.imencode(".png", np.clip(filtered, 0, 255).astype(np.uint8))
            if ok:
                atomic_write_bytes(self.session.out_dir / PNG, buf.tobytes())
        except OSError as e:
            self.notify(f"{png} not written: {e}", severity="warning")
        self.app.push_screen(PreviewScreen(before, after, captions, png))

    @staticmethod
    def lens(inputs, img):
        return inputs.lens.undistort(img) if inputs.lens is not None else img

    def first_gray(self, inputs):
        for fr in inputs.source:
            return self.lens(inputs, fr.image)
        raise ParameterError("video: the range holds no frame")

    def roi(self, inputs):
        return roi_and_mask(self.project, inputs)[0]

    @staticmethod
    def crop(img, roi):
        if roi is None:
            return img
        x0, y0, x1, y1 = roi
        return img[y0:y1, x0:x1]
