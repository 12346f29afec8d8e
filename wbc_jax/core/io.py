"""Files: input text read with one-line errors naming the file; results written atomically."""

from __future__ import annotations

import io
import json
import os
import pathlib
import tempfile

import numpy as np


def atomic_write_bytes(path: pathlib.Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        # mkstemp creates 0600; results get the user's normal permissions (0666 minus umask).
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _read_umask() -> int:
    try:  # Linux: no process-wide change
        for line in pathlib.Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def atomic_write_json(path: pathlib.Path, obj) -> None:
    atomic_write_bytes(path, _json_bytes(obj))


def write_new_json(path: pathlib.Path, obj) -> None:
    """Write ``obj`` as JSON to a file that must not exist yet (or already hold exactly this): a
    result names its gains file by path and sha256, so a gains file is never overwritten; a later
    campaign writes a new, named file (experiments/gains/README.md)."""
    path, data = pathlib.Path(path), _json_bytes(obj)
    if path.exists():
        if path.read_bytes() == data:
            return
        raise FileExistsError(
            f"{path} exists with other contents; results name it by its sha256, so it is never "
            "overwritten: write a new, named file"
        )
    atomic_write_bytes(path, data)


def _json_bytes(obj) -> bytes:
    return (json.dumps(obj, indent=2, default=jsonable) + "\n").encode()


def atomic_save_npz(path: pathlib.Path, **arrays) -> None:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def jsonable(x):
    """``json.dumps``'s ``default``: NumPy arrays and scalars as lists and Python numbers."""
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x)}")


def atomic_write_parquet(path: pathlib.Path, table) -> None:
    """Write a pandas DataFrame as Parquet, atomically."""
    buf = io.BytesIO()
    table.to_parquet(buf, index=False)
    atomic_write_bytes(path, buf.getvalue())


def atomic_save_figure(path: pathlib.Path, fig, dpi: int = 110) -> None:
    """Save a matplotlib Figure as PNG, atomically."""
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    atomic_write_bytes(path, buf.getvalue())


# The largest input file any job reads (gains, envelopes, summaries; YAML task files: loader.MAX_YAML_BYTES). The
# largest input file of the repository is a 270 kB limit summary: 4 MiB leaves 15x room.
MAX_FILE_BYTES = 4 * 2**20


def read_text(path, what: str, max_bytes: int | None = None) -> str:
    """The UTF-8 text of ``path``; one line naming ``what`` and the file when it cannot be read
    (missing, a folder, not readable, not UTF-8, longer than ``max_bytes``: None,
    :data:`MAX_FILE_BYTES`; counted while reading, so a device never ends)."""

    path, limit = pathlib.Path(path), MAX_FILE_BYTES if max_bytes is None else max_bytes
    try:
        with path.open("rb") as fh:
            data = fh.read(limit + 1)
        if len(data) > limit:
            raise ValueError(f"{what} file {path} is larger than {limit / 2**20:g} MiB, the limit of an input file")
        return data.decode("utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} file {path} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"{what} {path} is not a file (a directory?)") from None
    except PermissionError:
        raise ValueError(f"{what} file {path} is not readable (permission denied)") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{what} file {path} is not UTF-8 text (byte {err.start}: {err.reason})") from None
    except OSError as err:
        raise ValueError(f"{what} file {path} cannot be read ({err.strerror})") from None
