"""Text from users and files is decoded explicitly: UTF-8, or one InputError line.

Issue 14, item 10: non-UTF-8 bytes in ``--name``, in a source's file name, in ``remove``, in
``init``'s path or in a token file ended in ``UnicodeEncodeError``/``UnicodeDecodeError``
tracebacks. Python decodes arguments and file names with ``surrogateescape`` (a byte 0xff
becomes U+DCFF), so such a ``str`` exists but is not text. The CLI rows are in
``tests/cli/test_bad_input.py``; these are the shared checks themselves.
"""

from __future__ import annotations

import os

import pytest

from sprint_map.errors import InputError
from sprint_map.server.auth import load_token
from sprint_map.server.config import ServerConfig
from sprint_map.util.validation import decode_text, name_key, shown, validate_name

UNDECODABLE = b"a\xffb".decode("utf-8", "surrogateescape")  # what argv gives for a 0xff byte


def test_names_must_be_utf8_and_messages_stay_printable():
    with pytest.raises(InputError, match=r"^sequence name b'a\\xffb' is not UTF-8 text$"):
        validate_name(UNDECODABLE)
    with pytest.raises(InputError, match=r"^sequence name '\\ud800' is not UTF-8 text$"):
        validate_name("\ud800")  # a lone surrogate from JSON: no byte decodes to it
    with pytest.raises(InputError, match="an empty name is not a name"):
        validate_name("")
    validate_name("Nordland: vinter ❄")  # UTF-8 beyond ASCII is text
    assert shown(UNDECODABLE) == "b'a\\xffb'"
    assert decode_text(b"caf\xc3\xa9", "x") == "café"
    with pytest.raises(InputError, match=r"^map path b'\\xffmap' is not UTF-8 text$"):
        decode_text(b"\xffmap", "map path")


def test_name_lookups_find_nothing_for_what_cannot_be_a_name():
    assert name_key("") is None  # remove MAP '': an unknown sequence, not an LMDB error
    assert name_key("x" * 501) is None and name_key("a\nb") is None
    assert name_key("monday") == b"monday"
    with pytest.raises(InputError, match="not UTF-8"):
        name_key(UNDECODABLE)


def test_a_token_that_is_not_utf8_is_refused_without_showing_it(tmp_path, monkeypatch):
    token_file = tmp_path / "token"
    token_file.write_bytes(b"s3cr\xe9t\n")  # Latin-1
    with pytest.raises(InputError) as refused:
        load_token(ServerConfig(token_file=str(token_file)))
    assert str(refused.value) == f"token file {token_file} is not UTF-8 text"
    monkeypatch.setenv("SPRINT_MAP_TOKEN", os.fsdecode(b"s3cr\xe9t"))
    with pytest.raises(InputError, match=r"^\$SPRINT_MAP_TOKEN is not UTF-8 text$"):
        load_token(ServerConfig())
    token_file.write_bytes("s3crét\n".encode())
    assert load_token(ServerConfig(token_file=str(token_file))) == "s3crét"


def test_the_real_cli_gives_one_line_for_bytes_that_are_not_utf8(tmp_path):
    """Each case of the issue through the installed ``sprint-map`` with real bytes in argv and
    in file names (parallel processes; each starts in ~2 s): exit 13, one ``Error:`` line."""
    import shutil
    import subprocess

    import numpy as np

    from sprint_map.config import MapConfig
    from sprint_map.map import SprintMap

    exe = os.fsencode(shutil.which("sprint-map") or "sprint-map")
    root = os.fsencode(tmp_path)
    good = np.random.default_rng(3).standard_normal((4, 8)).astype(np.float32)
    np.save(tmp_path / "good.npy", good)
    np.save(os.fsdecode(root + b"/bad\xff.npy"), good)
    (tmp_path / "token").write_bytes(b"s3cr\xe9t\n")
    with SprintMap.create(tmp_path / "m", MapConfig(dim=8)) as m:
        m.add_sequence(good, name="first")
    cases = {
        "name": ([b"ingest", root + b"/m", root + b"/good.npy", b"--name", b"a\xffb"],
                 13, "sequence name b'a\\xffb' is not UTF-8 text"),
        "source-path": ([b"ingest", root + b"/m", root + b"/bad\xff.npy"],
                        13, "bad\\xff.npy' is not UTF-8 text"),
        "remove": ([b"remove", root + b"/m", b"\xff"], 13, "is not UTF-8 text"),
        "remove-empty": ([b"remove", root + b"/m", b""], 12, "no sequence named '' in the map"),
        "init-path": ([b"init", root + b"/new\xff.map", b"--dim", b"8"], 13,
                      "new\\xff.map' is not UTF-8 text"),
        "token-file": ([b"serve", root + b"/m", b"--token-file", root + b"/token"], 13,
                       f"token file {tmp_path / 'token'} is not UTF-8 text"),
    }
    procs = {}
    for name, (args, _, _) in cases.items():  # each writer its own copy of the map
        shutil.copytree(tmp_path / "m", tmp_path / name)
        args = [a.replace(root + b"/m", root + b"/" + name.encode()) for a in args]
        procs[name] = subprocess.Popen([exe, *args], stdout=subprocess.PIPE,
                                       stderr=subprocess.PIPE)
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        _, code, message = cases[name]
        lines = err.decode("utf-8", "backslashreplace").strip().splitlines()
        assert proc.returncode == code, (name, err)
        assert out == b"" and len(lines) == 1 and lines[0].startswith("Error: "), (name, err)
        assert message in lines[0], (name, lines)
    assert not os.path.exists(root + b"/new\xff.map")  # init made nothing
    for name in cases:
        with SprintMap.open(tmp_path / name, readonly=True) as m:
            assert [s.name for s in m.sequences()] == ["first"]
