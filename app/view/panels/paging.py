"""Long lists in a panel, a page at a time: a campus session has thousands of edges and hundreds of loops.

A markdown table or a dropdown of a thousand rows is sent whole to every browser on every refresh
and is unusable to scroll; a page of :data:`PAGE_ROWS` with a page number keeps both short. The page
number is one field per list; a list that shrinks keeps the page in range.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import viser

T = TypeVar("T")

PAGE_ROWS = 25


def page_bounds(count: int, page: int, rows: int = PAGE_ROWS) -> tuple[int, int, int]:
    """(first, stop, pages) of 1-based ``page`` of ``count`` items, the page clamped to 1..pages."""
    pages = max(1, -(-count // rows))
    first = (min(max(page, 1), pages) - 1) * rows
    return first, min(count, first + rows), pages


class Pager:
    """A page-number field for one list; :meth:`page` gives the current page's items and a caption."""

    def __init__(self, gui: viser.GuiApi, label: str, on_change: Callable[[], None]) -> None:
        self.number = gui.add_number(label, 1, min=1, step=1)
        self.number.on_update(lambda _: on_change())

    def page(self, items: Sequence[T], noun: str) -> tuple[list[T], str]:
        first, stop, pages = page_bounds(len(items), int(self.number.value))
        self.number.max = pages
        if int(self.number.value) > pages:
            self.number.value = pages  # type: ignore[misc]
        caption = f"{noun} {first + 1}–{stop} of {len(items)} (page {first // PAGE_ROWS + 1} of {pages})"
        return list(items[first:stop]), caption if pages > 1 else ""
