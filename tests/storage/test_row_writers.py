"""Both writers of uncommitted rows pass the one contract
(:class:`tests.helpers.contracts.RowWriterContract`): one sequence (``SequenceWriter``) and a
group of them committed at once (``GroupWriter``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from sprint_map.storage.group_writer import GroupWriter
from sprint_map.storage.sequence_writer import SequenceWriter
from sprint_map.storage.store import MapStore
from tests.helpers.contracts import RowWriterContract


class TestSequenceWriter(RowWriterContract):
    """Rows appended in two batches."""

    def begin(self, store: MapStore, name: str) -> Any:
        return SequenceWriter(store, name=name)

    def write(self, writer: Any, rows: np.ndarray) -> None:
        half = len(rows) // 2
        writer.append(rows[:half])
        writer.append(rows[half:])

    def commit(self, writer: Any) -> list[Any]:
        return [writer.commit()]


class TestGroupWriter(RowWriterContract):
    """One sequence added to the group, as an iterator of three batches."""

    def begin(self, store: MapStore, name: str) -> Any:
        self.name = name
        return GroupWriter(store)

    def write(self, writer: Any, rows: np.ndarray) -> None:
        writer.add(iter(np.array_split(rows, 3)), name=self.name)

    def commit(self, writer: Any) -> list[Any]:
        return writer.commit()
