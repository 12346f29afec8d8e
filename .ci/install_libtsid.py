"""Install libtsid (TSID's C++ library) on any CPython 3, before ``pip install -e ".[dev]"``.

Why: the dev extra's ``tsid==1.10.0`` (the TSID peer, benchmarks/tsid_baseline/) has cp311 wheels,
but it requires ``libtsid==1.10.0``, and PyPI holds that only as wheels tagged cp314-cp314 (plus an
sdist whose build clones jrl-cmakemodules from GitHub and compiles TSID). The wheel holds no Python
(lib/libtsid.so, headers, CMake and pkg-config files under cmeel.prefix): the tag is a packaging
slip. This script downloads that wheel for this machine's platform, retags it py3-none (the WHEEL
file, its RECORD line and the file name) and installs it with the Pinocchio it was built against;
pip then finds libtsid==1.10.0 installed when it resolves the dev extra. Idempotent.

    python3 .ci/install_libtsid.py
"""

from __future__ import annotations

import base64
import hashlib
import pathlib
import subprocess
import sys
import tempfile
import zipfile
from importlib import metadata

LIBTSID = "1.10.0"
LIBPINOCCHIO = "4.0.0"  # libtsid 1.10.0 was built against it (pyproject's dev extra pins pin==4.0.0)
WHEEL_TAG = "cp314-cp314"


def _record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def retag(wheel: pathlib.Path, out_dir: pathlib.Path) -> pathlib.Path:
    """A copy of ``wheel`` tagged py3-none-<platform> in ``out_dir``; ValueError if it is not a
    cp314-cp314 wheel or holds Python files."""
    name = wheel.name
    if f"-{WHEEL_TAG}-" not in name:
        raise ValueError(f"{name}: expected a {WHEEL_TAG} wheel")
    platform = name[: -len(".whl")].split(f"-{WHEEL_TAG}-", 1)[1]
    new_name = name.replace(f"-{WHEEL_TAG}-", "-py3-none-")
    with zipfile.ZipFile(wheel) as src:
        python_files = [n for n in src.namelist() if n.endswith((".py", ".so")) and "/python3" in n]
        if python_files:
            raise ValueError(f"{name} holds Python files {python_files[:3]}: retagging would be wrong")
        wheel_file = next(n for n in src.namelist() if n.endswith(".dist-info/WHEEL"))
        record_file = next(n for n in src.namelist() if n.endswith(".dist-info/RECORD"))
        wheel_text = src.read(wheel_file).decode().replace(f"Tag: {WHEEL_TAG}-{platform}", f"Tag: py3-none-{platform}")
        if f"Tag: py3-none-{platform}" not in wheel_text:
            raise ValueError(f"{name}: no 'Tag: {WHEEL_TAG}-{platform}' line in {wheel_file}")
        wheel_bytes = wheel_text.encode()
        record = [
            f"{wheel_file},{_record_hash(wheel_bytes)},{len(wheel_bytes)}"
            if line.startswith(wheel_file + ",")
            else line
            for line in src.read(record_file).decode().splitlines()
        ]
        out = out_dir / new_name
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
            for info in src.infolist():
                data = src.read(info.filename)
                if info.filename == wheel_file:
                    data = wheel_bytes
                elif info.filename == record_file:
                    data = ("\n".join(record) + "\n").encode()
                dst.writestr(info, data)
    return out


def main(argv=None) -> None:
    import argparse

    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args(argv)  # --help: nothing installed
    try:
        if metadata.version("libtsid") == LIBTSID:
            print(f"libtsid {LIBTSID} is installed")
            return
    except metadata.PackageNotFoundError:
        pass
    pip = [sys.executable, "-m", "pip"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        subprocess.run(
            [
                *pip,
                "download",
                f"libtsid=={LIBTSID}",
                "--no-deps",
                "--only-binary=:all:",
                "--python-version",
                "3.14",
                "--implementation",
                "cp",
                "--abi",
                "cp314",
                "--dest",
                str(tmp / "dl"),
            ],
            check=True,
        )
        (wheel,) = (tmp / "dl").glob("libtsid-*.whl")
        fixed = retag(wheel, tmp)
        subprocess.run([*pip, "install", str(fixed), f"libpinocchio=={LIBPINOCCHIO}"], check=True)
    print(f"installed {fixed.name}")


if __name__ == "__main__":
    main()
