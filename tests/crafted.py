"""Crafted pickles for the security tests: memmap folders whose loading would run code.

Each crafted pickle creates a marker file when unpickled; a test that reads a crafted folder checks that
the marker never appears.
"""

from __future__ import annotations

import json
import pathlib
import pickle

NON_TENSOR_DATA = "<class 'tensordict.tensorclass.NonTensorData'>"


class TouchOnUnpickle:
    """Unpickling this calls ``path.touch()``: the stand-in for arbitrary code."""

    def __init__(self, path: pathlib.Path) -> None:
        self.path = path

    def __reduce__(self):
        return pathlib.Path.touch, (self.path,)


def edit_json(path: pathlib.Path, **entries) -> None:
    path.write_text(json.dumps({**json.loads(path.read_text()), **entries}))


def pickled_non_tensor(folder: pathlib.Path, marker: pathlib.Path) -> None:
    """Make ``folder`` a memmap ``NonTensorData`` whose pickle touches ``marker`` (as tensordict lays it out)."""
    folder.mkdir(exist_ok=True)
    (folder / "meta.json").write_text(json.dumps({"_type": NON_TENSOR_DATA, "_is_non_tensor": True,
                                                  "_metadata": None}))
    (folder / "other.pickle").write_bytes(pickle.dumps({"data": TouchOnUnpickle(marker)}))


def graft_entry(data: pathlib.Path, marker: pathlib.Path) -> pathlib.Path:
    """A ``NonTensorData`` entry beside the tensors (what ``td["x"] = NonTensorData(obj); td.memmap_()`` writes)."""
    pickled_non_tensor(data / "evil", marker)
    edit_json(data / "meta.json", evil={"type": "NonTensorData"})
    return data / "meta.json"


def disguise_subfolder(data: pathlib.Path, marker: pathlib.Path) -> pathlib.Path:
    """An entry that claims to be a TensorDict folder, whose own meta.json names another class."""
    pickled_non_tensor(data / "evil", marker)
    edit_json(data / "meta.json", evil={"type": "TensorDict"})
    return data / "evil" / "meta.json"


def replace_root(data: pathlib.Path, marker: pathlib.Path) -> pathlib.Path:
    """The memmap folder itself declared a NonTensorData."""
    (data / "other.pickle").write_bytes(pickle.dumps({"data": TouchOnUnpickle(marker)}))
    edit_json(data / "meta.json", _type=NON_TENSOR_DATA)
    return data / "meta.json"


CRAFTS = {"entry": graft_entry, "disguised-subfolder": disguise_subfolder, "root-type": replace_root}
