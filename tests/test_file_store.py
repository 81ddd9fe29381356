"""FileStore: the file-system side of FileDirectoryType/FileType (OPC 10000-20) without OPC UA."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from uacell.core.errors import CallError
from uacell.core.file_store import (
    MODE_APPEND,
    MODE_ERASE_EXISTING,
    MODE_READ,
    MODE_WRITE,
    TEMP_PREFIX,
    Change,
    Entry,
    FileStore,
)

R, W, E, A = MODE_READ, MODE_WRITE, MODE_ERASE_EXISTING, MODE_APPEND
S1, S2 = "session-1", "session-2"


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Everything on disk below root, temporaries included: files -> content, directories -> None."""
    out: dict[str, bytes | None] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for d in dirnames:
            out[(Path(dirpath) / d).relative_to(root).as_posix()] = None
        for f in filenames:
            p = Path(dirpath) / f
            out[p.relative_to(root).as_posix()] = p.read_bytes()
    return out


def temporaries(root: Path) -> list[str]:
    return [p for p in snapshot(root) if p.rpartition("/")[2].startswith(TEMP_PREFIX)]


def check(exc: pytest.ExceptionInfo[CallError], status: str, argument: int | None = None) -> None:
    assert exc.value.status == status, exc.value.message
    assert exc.value.argument == argument


@pytest.fixture
def root(tmp_path: Path) -> Path:
    base = tmp_path / "programs"
    (base / "sub" / "deep").mkdir(parents=True)
    (base / "a.robot").write_bytes(b"hello")
    (base / "sub" / "b.robot").write_bytes(b"0123456789")
    (base / "sub" / "deep" / "c.robot").write_bytes(b"c")
    return base


@pytest.fixture(autouse=True)
def close_every_store(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Tests leave handles open on purpose; their files are closed when the test ends."""
    made: list[FileStore] = []
    original = FileStore.__init__

    def init(self: FileStore, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(FileStore, "__init__", init)
    yield
    for store in made:
        store.close_all()


@pytest.fixture
def store(root: Path) -> FileStore:
    return FileStore(root)


@pytest.fixture
def changes(store: FileStore) -> list[Change]:
    seen: list[Change] = []
    store.listeners.append(seen.append)
    return seen


# ---------------------------------------------------------------- listing and start-up


def test_entries_list_files_and_directories_parents_first(store: FileStore) -> None:
    assert store.entries() == [
        Entry("a.robot", False, 5, True),
        Entry("sub", True, 0, True),
        Entry("sub/b.robot", False, 10, True),
        Entry("sub/deep", True, 0, True),
        Entry("sub/deep/c.robot", False, 1, True),
    ]
    assert [e.relpath for e in store.entries("sub")] == ["sub/b.robot", "sub/deep", "sub/deep/c.robot"]
    assert store.entry("sub/b.robot").name == "b.robot"


def test_entries_report_read_only_files(store: FileStore, monkeypatch: pytest.MonkeyPatch) -> None:
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, m: False if str(p).endswith("a.robot") else real_access(p, m))
    assert store.entry("a.robot").writable is False
    assert store.entry("sub/b.robot").writable is True


def test_start_removes_leftover_temporaries_and_hides_them(root: Path) -> None:
    (root / f"{TEMP_PREFIX}x").write_bytes(b"half a program")
    (root / "sub" / f"{TEMP_PREFIX}dir").mkdir()
    (root / "sub" / f"{TEMP_PREFIX}dir" / "f").write_bytes(b"x")
    FileStore(root)
    assert temporaries(root) == []
    assert (root / "a.robot").read_bytes() == b"hello"


def test_temporaries_and_symlinks_are_not_listed(store: FileStore, root: Path, tmp_path: Path) -> None:
    h = store.open(S1, "a.robot", W)  # creates a private temporary next to a.robot
    assert len(temporaries(root)) == 1
    outside = tmp_path / "secret"
    outside.write_bytes(b"secret")
    (root / "link").symlink_to(outside)
    (root / "linkdir").symlink_to(tmp_path)
    listed = [e.relpath for e in store.entries()]
    assert listed == ["a.robot", "sub", "sub/b.robot", "sub/deep", "sub/deep/c.robot"]
    (root / "sub" / "notes.txt").write_bytes(b"x")
    (root / "sub" / "dir.robot").mkdir()
    assert store.files(".robot") == ["a.robot", "sub/b.robot", "sub/deep/c.robot"]  # files only, no link
    assert store.files() == ["a.robot", "sub/b.robot", "sub/deep/c.robot", "sub/notes.txt"]
    store.close(S1, h)


def test_a_files_listing_is_kept_until_a_directory_changes_on_disk(store: FileStore, root: Path) -> None:
    import os
    import time

    def age(path: Path) -> None:  # as if the directory had last changed a minute ago
        old = time.time() - 60
        os.utime(path, (old, old))

    for d in (root, root / "sub", root / "sub" / "deep"):
        age(d)
    first = store.files(".robot")
    assert first == ["a.robot", "sub/b.robot", "sub/deep/c.robot"]
    assert store.files(".robot") == first  # from the kept listing
    (root / "sub" / "deep" / "d.robot").write_bytes(b"added behind the server's back")
    assert store.files(".robot") == [*first, "sub/deep/d.robot"]  # a directory's time moved: read again
    (root / "a.robot").unlink()
    assert store.files(".robot") == ["sub/b.robot", "sub/deep/c.robot", "sub/deep/d.robot"]
    age(root)
    age(root / "sub" / "deep")
    store.files(".robot")
    (root / "sub" / "new").mkdir()
    (root / "sub" / "new" / "e.robot").write_bytes(b"x")  # a new subdirectory: its parent changed
    assert "sub/new/e.robot" in store.files(".robot")


def test_missing_root_is_created(tmp_path: Path) -> None:
    store = FileStore(tmp_path / "new" / "programs")
    assert store.entries() == []
    assert (tmp_path / "new" / "programs").is_dir()


# ---------------------------------------------------------------- Open modes


@pytest.mark.parametrize("mode", [0, E, A, E | A, R | E, R | A, 16, R | 0x10, 0x81, 255, -1, 256])
def test_invalid_open_modes_are_bad_invalid_argument(store: FileStore, root: Path, mode: int) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.open(S1, "a.robot", mode)
    check(exc, "BadInvalidArgument", argument=0)
    assert snapshot(root) == before
    assert store.open_count("a.robot") == 0


@pytest.mark.parametrize("mode", [R, W, R | W, W | E, R | W | E, W | A, R | W | A, R | W | E | A])
def test_valid_open_modes_give_a_handle(store: FileStore, mode: int) -> None:
    h = store.open(S1, "a.robot", mode)
    assert isinstance(h, int) and 0 < h <= 0xFFFFFFFF
    assert store.open_count("a.robot") == 1
    store.close(S1, h)
    assert store.open_count("a.robot") == 0


def test_open_unknown_file_or_directory_is_bad_not_found(store: FileStore) -> None:
    for relpath in ["missing.robot", "sub/missing", "nodir/a.robot", "sub", ""]:
        with pytest.raises(CallError) as exc:
            store.open(S1, relpath, R)
        check(exc, "BadNotFound")


def test_open_read_only_file_for_writing_is_bad_not_writable(store: FileStore, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "access", lambda p, m: m != os.W_OK)
    with pytest.raises(CallError) as exc:
        store.open(S1, "a.robot", W)
    check(exc, "BadNotWritable")


def test_open_unreadable_file_for_reading_is_bad_not_readable(
    store: FileStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(os, "access", lambda p, m: m != os.R_OK)
    with pytest.raises(CallError) as exc:
        store.open(S1, "a.robot", R)
    check(exc, "BadNotReadable")


# ---------------------------------------------------------------- Read / Write / positions


def test_read_in_chunks_until_end_of_file(store: FileStore) -> None:
    h = store.open(S1, "sub/b.robot", R)
    assert store.read(S1, h, 4) == b"0123"
    assert store.get_position(S1, h) == 4
    assert store.read(S1, h, 100) == b"456789"
    assert store.read(S1, h, 100) == b""
    assert store.get_position(S1, h) == 10


def test_read_is_capped_at_max_read(root: Path) -> None:
    store = FileStore(root, max_read=3)
    h = store.open(S1, "sub/b.robot", R)
    assert store.read(S1, h, 1000) == b"012"
    assert store.read(S1, h, 1000) == b"345"


@pytest.mark.parametrize("length", [0, -1])
def test_read_non_positive_length_is_bad_invalid_argument(store: FileStore, length: int) -> None:
    h = store.open(S1, "a.robot", R)
    with pytest.raises(CallError) as exc:
        store.read(S1, h, length)
    check(exc, "BadInvalidArgument", argument=1)
    assert store.get_position(S1, h) == 0


def test_read_on_write_only_handle_is_bad_invalid_state(store: FileStore) -> None:
    h = store.open(S1, "a.robot", W)
    with pytest.raises(CallError) as exc:
        store.read(S1, h, 5)
    check(exc, "BadInvalidState")


def test_write_on_read_only_handle_is_bad_invalid_state(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", R)
    with pytest.raises(CallError) as exc:
        store.write(S1, h, b"x")
    check(exc, "BadInvalidState")
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b"hello"


def test_write_starts_from_old_content_and_replaces_on_close(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", R | W)
    store.write(S1, h, b"J")
    assert store.get_position(S1, h) == 1
    assert (root / "a.robot").read_bytes() == b"hello"  # nothing visible before Close
    store.set_position(S1, h, 0)
    assert store.read(S1, h, 10) == b"Jello"  # the handle reads its own writes
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b"Jello"
    assert store.entry("a.robot").size == 5
    assert temporaries(root) == []


def test_erase_existing_starts_empty(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", W | E)
    assert store.get_position(S1, h) == 0
    store.write(S1, h, b"new")
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b"new"


def test_erase_existing_and_close_without_writing_empties_the_file(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", W | E)
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b""


def test_append_starts_at_end(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", W | A)
    assert store.get_position(S1, h) == 5
    store.write(S1, h, b" world")
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b"hello world"


def test_write_of_empty_data_changes_nothing(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", W)
    store.write(S1, h, b"")
    assert store.get_position(S1, h) == 0
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b"hello"


def test_set_position_past_end_goes_to_end(store: FileStore) -> None:
    h = store.open(S1, "sub/b.robot", R)
    store.set_position(S1, h, 3)
    assert store.read(S1, h, 2) == b"34"
    store.set_position(S1, h, 1_000_000)
    assert store.get_position(S1, h) == 10
    with pytest.raises(CallError) as exc:
        store.set_position(S1, h, -1)
    check(exc, "BadInvalidArgument", argument=1)
    assert store.get_position(S1, h) == 10


def test_set_position_on_write_handle_counts_unflushed_writes(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", W | E)
    store.write(S1, h, b"abcdef")
    store.set_position(S1, h, 100)
    assert store.get_position(S1, h) == 6
    store.set_position(S1, h, 2)
    store.write(S1, h, b"XY")
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b"abXYef"


def test_commit_keeps_the_file_permissions(store: FileStore, root: Path) -> None:
    os.chmod(root / "a.robot", 0o640)
    h = store.open(S1, "a.robot", W | E)
    store.write(S1, h, b"x")
    store.close(S1, h)
    assert (root / "a.robot").stat().st_mode & 0o777 == 0o640


# ---------------------------------------------------------------- sharing rules and handles


def test_several_readers_but_one_writer(store: FileStore) -> None:
    r1 = store.open(S1, "a.robot", R)
    r2 = store.open(S2, "a.robot", R)
    assert r1 != r2
    assert store.open_count("a.robot") == 2
    with pytest.raises(CallError) as exc:
        store.open(S2, "a.robot", R | W)
    check(exc, "BadNotWritable")  # "open for writing ... already opened" (10000-20 4.2.2)
    store.close(S1, r1)
    store.close(S2, r2)
    w = store.open(S1, "a.robot", W)
    with pytest.raises(CallError) as exc:
        store.open(S2, "a.robot", R)
    check(exc, "BadNotReadable")  # "open for reading ... already opened for writing"
    with pytest.raises(CallError) as exc:
        store.open(S1, "a.robot", W)
    check(exc, "BadNotWritable")
    assert store.open_count("a.robot") == 1
    store.close(S1, w)
    assert store.open_count("a.robot") == 0


def test_other_sessions_handles_are_invalid(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", R | W)
    for call in (
        lambda: store.read(S2, h, 1),
        lambda: store.write(S2, h, b"x"),
        lambda: store.get_position(S2, h),
        lambda: store.set_position(S2, h, 0),
        lambda: store.close(S2, h),
    ):
        with pytest.raises(CallError) as exc:
            call()
        check(exc, "BadInvalidArgument", argument=0)
    # Still valid, and unaffected, for its own session.
    assert store.get_position(S1, h) == 0
    assert store.read(S1, h, 5) == b"hello"
    store.close(S1, h)
    assert (root / "a.robot").read_bytes() == b"hello"


def test_unknown_and_closed_handles_are_bad_invalid_argument(store: FileStore) -> None:
    h = store.open(S1, "a.robot", R)
    store.close(S1, h)
    for bad in (h, 0, 12345, -1, "1"):
        with pytest.raises(CallError) as exc:
            store.close(S1, bad)  # type: ignore[arg-type]
        check(exc, "BadInvalidArgument", argument=0)
        with pytest.raises(CallError) as exc:
            store.read(S1, bad, 1)  # type: ignore[arg-type]
        check(exc, "BadInvalidArgument", argument=0)


def test_handles_are_unique_over_sessions(store: FileStore) -> None:
    handles = [store.open(s, "sub/b.robot", R) for s in (S1, S2, S1, S2)]
    assert len(set(handles)) == 4
    assert 0 not in handles


def test_close_session_discards_uncommitted_writes(store: FileStore, root: Path) -> None:
    w = store.open(S1, "a.robot", W | E)
    store.write(S1, w, b"never committed")
    r1 = store.open(S1, "sub/b.robot", R)
    r2 = store.open(S2, "sub/b.robot", R)
    assert store.close_session(S1) == 2
    assert (root / "a.robot").read_bytes() == b"hello"
    assert temporaries(root) == []
    assert store.open_count("a.robot") == 0
    assert store.open_count("sub/b.robot") == 1
    with pytest.raises(CallError) as exc:
        store.read(S1, r1, 1)
    check(exc, "BadInvalidArgument", argument=0)
    assert store.read(S2, r2, 3) == b"012"  # the other session is untouched
    assert store.close_session(S1) == 0
    # The file is free again for writing.
    store.close(S2, store.open(S2, "a.robot", W))


# ---------------------------------------------------------------- durability


def test_crash_before_close_keeps_old_content(root: Path) -> None:
    store = FileStore(root)
    h = store.open(S1, "a.robot", W | E)
    store.write(S1, h, b"half a prog")
    assert temporaries(root) != []
    # The server dies here: no Close, no close_session. A new store is the restart.
    del store
    restarted = FileStore(root)
    assert (root / "a.robot").read_bytes() == b"hello"
    assert temporaries(root) == []
    assert restarted.entry("a.robot").size == 5


def test_failure_during_replace_keeps_old_content(
    store: FileStore, root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    h = store.open(S1, "a.robot", W | E)
    store.write(S1, h, b"new content")

    def broken_replace(src: object, dst: object) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(CallError) as exc:
        store.close(S1, h)
    check(exc, "BadUnexpectedError")
    assert (root / "a.robot").read_bytes() == b"hello"
    assert temporaries(root) == []
    assert store.open_count("a.robot") == 0
    with pytest.raises(CallError) as exc:
        store.close(S1, h)  # the handle is gone
    check(exc, "BadInvalidArgument", argument=0)
    monkeypatch.undo()
    h = store.open(S1, "a.robot", W)  # and the file can be written again
    store.close(S1, h)


def test_failure_during_fsync_keeps_old_content(store: FileStore, root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    h = store.open(S1, "a.robot", W | E)
    store.write(S1, h, b"new content")

    def broken_fsync(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    with pytest.raises(CallError) as exc:
        store.close(S1, h)
    check(exc, "BadUnexpectedError")
    assert (root / "a.robot").read_bytes() == b"hello"
    assert temporaries(root) == []


def test_commit_syncs_file_before_rename_and_directory_after(
    store: FileStore, root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        log.append("fsync-dir" if Path(f"/proc/self/fd/{fd}").resolve().is_dir() else "fsync-file")
        real_fsync(fd)

    def replace(src: str, dst: str) -> None:
        log.append("replace")
        real_replace(src, dst)

    h = store.open(S1, "a.robot", W | E)
    store.write(S1, h, b"x")
    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    store.close(S1, h)
    assert log == ["fsync-file", "replace", "fsync-dir"]


# ---------------------------------------------------------------- CreateFile / CreateDirectory

BAD_NAMES = ["", ".", "..", "a/b", "/abs", "a\\b", "nul\0", f"{TEMP_PREFIX}x", "x" * 256, None, 7]


def test_create_file_makes_an_empty_file(store: FileStore, root: Path, changes: list[Change]) -> None:
    relpath, handle = store.create_file(S1, "sub", "new.robot", False)
    assert (relpath, handle) == ("sub/new.robot", None)
    assert (root / "sub" / "new.robot").read_bytes() == b""
    assert store.entry("sub/new.robot") == Entry("sub/new.robot", False, 0, True)
    assert changes == [Change("added", "sub/new.robot", False)]


def test_create_file_with_open_gives_a_read_write_handle(store: FileStore, root: Path) -> None:
    relpath, handle = store.create_file(S1, "", "p.robot", True)
    assert relpath == "p.robot" and handle is not None
    assert store.open_count("p.robot") == 1
    store.write(S1, handle, b"PROGRAM p")
    store.set_position(S1, handle, 0)
    assert store.read(S1, handle, 100) == b"PROGRAM p"
    assert (root / "p.robot").read_bytes() == b""
    store.close(S1, handle)
    assert (root / "p.robot").read_bytes() == b"PROGRAM p"


@pytest.mark.parametrize("existing", ["a.robot", "sub"])
def test_create_file_with_existing_name_is_duplicate(store: FileStore, root: Path, existing: str) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.create_file(S1, "", existing, True)
    check(exc, "BadBrowseNameDuplicated", argument=0)
    assert snapshot(root) == before
    assert store.open_count(existing) == 0


@pytest.mark.parametrize("name", BAD_NAMES)
def test_create_file_with_bad_name_is_invalid_argument(store: FileStore, root: Path, name: object) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.create_file(S1, "", name, False)  # type: ignore[arg-type]
    check(exc, "BadInvalidArgument", argument=0)
    assert exc.value.argument_status == "BadBrowseNameInvalid"
    assert snapshot(root) == before


def test_create_file_in_missing_directory_is_not_found(store: FileStore) -> None:
    for parent in ["missing", "a.robot"]:
        with pytest.raises(CallError) as exc:
            store.create_file(S1, parent, "x", False)
        check(exc, "BadNotFound")


def test_create_directory(store: FileStore, root: Path, changes: list[Change]) -> None:
    assert store.create_directory("sub", "cells") == "sub/cells"
    assert (root / "sub" / "cells").is_dir()
    assert store.create_file(S1, "sub/cells", "x.robot", False) == ("sub/cells/x.robot", None)
    assert changes == [Change("added", "sub/cells", True), Change("added", "sub/cells/x.robot", False)]


@pytest.mark.parametrize("name", ["sub", "a.robot"])
def test_create_directory_with_existing_name_is_duplicate(store: FileStore, root: Path, name: str) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.create_directory("", name)
    check(exc, "BadBrowseNameDuplicated", argument=0)
    assert snapshot(root) == before


@pytest.mark.parametrize("name", BAD_NAMES)
def test_create_directory_with_bad_name_is_invalid_argument(store: FileStore, root: Path, name: object) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.create_directory("sub", name)  # type: ignore[arg-type]
    check(exc, "BadInvalidArgument", argument=0)
    assert snapshot(root) == before


# ---------------------------------------------------------------- Delete


def test_delete_file(store: FileStore, root: Path, changes: list[Change]) -> None:
    store.delete("sub/b.robot")
    assert not (root / "sub" / "b.robot").exists()
    assert changes == [Change("removed", "sub/b.robot", False)]


def test_delete_directory_tree_children_first(store: FileStore, root: Path, changes: list[Change]) -> None:
    store.delete("sub")
    assert snapshot(root) == {"a.robot": b"hello"}
    assert changes == [
        Change("removed", "sub/deep/c.robot", False),
        Change("removed", "sub/deep", True),
        Change("removed", "sub/b.robot", False),
        Change("removed", "sub", True),
    ]


def test_delete_unknown_is_not_found(store: FileStore) -> None:
    with pytest.raises(CallError) as exc:
        store.delete("sub/none.robot")
    check(exc, "BadNotFound", argument=0)


def test_delete_root_is_refused(store: FileStore, root: Path) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.delete("")
    check(exc, "BadInvalidArgument", argument=0)
    assert snapshot(root) == before


@pytest.mark.parametrize("target", ["sub/deep/c.robot", "sub/deep", "sub"])
def test_delete_of_open_file_or_its_directory_is_invalid_state(store: FileStore, root: Path, target: str) -> None:
    h = store.open(S2, "sub/deep/c.robot", R)
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.delete(target)
    check(exc, "BadInvalidState", argument=0)
    assert snapshot(root) == before
    assert store.read(S2, h, 1) == b"c"


# ---------------------------------------------------------------- MoveOrCopy


def test_rename_in_place(store: FileStore, root: Path, changes: list[Change]) -> None:
    assert store.move_or_copy("a.robot", "", False, "renamed.robot") == "renamed.robot"
    assert (root / "renamed.robot").read_bytes() == b"hello"
    assert not (root / "a.robot").exists()
    assert changes == [Change("removed", "a.robot", False), Change("added", "renamed.robot", False)]


def test_move_directory_keeps_name_when_new_name_empty(store: FileStore, root: Path, changes: list[Change]) -> None:
    store.create_directory("", "archive")
    changes.clear()
    assert store.move_or_copy("sub/deep", "archive", False, "") == "archive/deep"
    assert (root / "archive" / "deep" / "c.robot").read_bytes() == b"c"
    assert not (root / "sub" / "deep").exists()
    assert changes == [
        Change("removed", "sub/deep/c.robot", False),
        Change("removed", "sub/deep", True),
        Change("added", "archive/deep", True),
        Change("added", "archive/deep/c.robot", False),
    ]


def test_copy_file_and_tree(store: FileStore, root: Path) -> None:
    assert store.move_or_copy("a.robot", "sub", True, None) == "sub/a.robot"
    assert store.move_or_copy("sub", "", True, "sub2") == "sub2"
    assert (root / "a.robot").read_bytes() == b"hello"
    assert (root / "sub2" / "a.robot").read_bytes() == b"hello"
    assert (root / "sub2" / "deep" / "c.robot").read_bytes() == b"c"
    assert (root / "sub" / "b.robot").read_bytes() == b"0123456789"
    assert temporaries(root) == []


def test_copy_of_file_being_written_copies_committed_content(store: FileStore, root: Path) -> None:
    h = store.open(S1, "a.robot", W | E)
    store.write(S1, h, b"draft")
    store.move_or_copy("a.robot", "", True, "copy.robot")
    assert (root / "copy.robot").read_bytes() == b"hello"
    assert temporaries(root) != []  # the writer's private copy, not a leftover of the copy
    store.close(S1, h)
    assert temporaries(root) == []


@pytest.mark.parametrize("create_copy", [False, True])
def test_move_or_copy_onto_existing_name_is_duplicate(store: FileStore, root: Path, create_copy: bool) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.move_or_copy("a.robot", "sub", create_copy, "b.robot")
    check(exc, "BadBrowseNameDuplicated", argument=3)
    with pytest.raises(CallError) as exc:
        store.move_or_copy("sub/b.robot", "sub", create_copy, None)
    check(exc, "BadBrowseNameDuplicated")
    assert snapshot(root) == before


def test_move_or_copy_not_found(store: FileStore, root: Path) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.move_or_copy("none.robot", "sub", False, None)
    check(exc, "BadNotFound", argument=0)
    with pytest.raises(CallError) as exc:
        store.move_or_copy("a.robot", "nodir", False, None)
    check(exc, "BadNotFound", argument=1)
    with pytest.raises(CallError) as exc:
        store.move_or_copy("a.robot", "sub/b.robot", False, None)  # a file is not a directory
    check(exc, "BadNotFound", argument=1)
    assert snapshot(root) == before


@pytest.mark.parametrize("name", [n for n in BAD_NAMES if n not in ("", None)])
def test_move_or_copy_bad_new_name(store: FileStore, root: Path, name: object) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.move_or_copy("a.robot", "", False, name)  # type: ignore[arg-type]
    check(exc, "BadInvalidArgument", argument=3)
    assert snapshot(root) == before


@pytest.mark.parametrize("create_copy", [False, True])
def test_directory_into_itself_is_refused(store: FileStore, root: Path, create_copy: bool) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        store.move_or_copy("sub", "sub/deep", create_copy, None)
    check(exc, "BadInvalidArgument", argument=1)
    assert snapshot(root) == before


def test_move_of_open_file_is_invalid_state(store: FileStore, root: Path) -> None:
    h = store.open(S1, "sub/b.robot", R)
    before = snapshot(root)
    for src in ["sub/b.robot", "sub"]:
        with pytest.raises(CallError) as exc:
            store.move_or_copy(src, "", False, "elsewhere")
        check(exc, "BadInvalidState", argument=0)
    assert snapshot(root) == before
    assert store.read(S1, h, 2) == b"01"


def test_move_or_copy_root_is_refused(store: FileStore) -> None:
    with pytest.raises(CallError) as exc:
        store.move_or_copy("", "sub", True, "x")
    check(exc, "BadInvalidArgument", argument=0)


# ---------------------------------------------------------------- protect hook (the loaded program)


@pytest.fixture
def loaded(root: Path) -> FileStore:
    return FileStore(root, protect=lambda relpath: relpath == "sub/b.robot")


def test_protected_file_cannot_be_opened_for_writing(loaded: FileStore, root: Path) -> None:
    for mode in [W, R | W, W | E, W | A]:
        with pytest.raises(CallError) as exc:
            loaded.open(S1, "sub/b.robot", mode)
        check(exc, "BadInvalidState")
    assert loaded.open_count("sub/b.robot") == 0
    assert temporaries(root) == []
    h = loaded.open(S1, "sub/b.robot", R)  # reading it is fine
    assert loaded.read(S1, h, 3) == b"012"


@pytest.mark.parametrize("target", ["sub/b.robot", "sub"])
def test_protected_file_cannot_be_deleted_or_moved(loaded: FileStore, root: Path, target: str) -> None:
    before = snapshot(root)
    with pytest.raises(CallError) as exc:
        loaded.delete(target)
    check(exc, "BadInvalidState", argument=0)
    with pytest.raises(CallError) as exc:
        loaded.move_or_copy(target, "", False, "moved")
    check(exc, "BadInvalidState", argument=0)
    assert snapshot(root) == before


def test_protected_file_can_be_copied(loaded: FileStore, root: Path) -> None:
    assert loaded.move_or_copy("sub/b.robot", "", True, None) == "b.robot"
    assert (root / "b.robot").read_bytes() == b"0123456789"


def test_protected_file_cannot_be_overwritten_by_create_file(loaded: FileStore, root: Path) -> None:
    with pytest.raises(CallError) as exc:
        loaded.create_file(S1, "sub", "b.robot", True)
    check(exc, "BadBrowseNameDuplicated", argument=0)
    assert (root / "sub" / "b.robot").read_bytes() == b"0123456789"


def test_file_loaded_while_open_for_writing_is_not_overwritten(store: FileStore, root: Path) -> None:
    h = store.open(S1, "sub/b.robot", W | E)
    store.write(S1, h, b"before load")
    store.protect = lambda relpath: relpath == "sub/b.robot"  # the program is loaded now
    with pytest.raises(CallError) as exc:
        store.write(S1, h, b"after load")
    check(exc, "BadNotWritable")
    with pytest.raises(CallError) as exc:
        store.close(S1, h)
    check(exc, "BadInvalidState")
    assert (root / "sub" / "b.robot").read_bytes() == b"0123456789"
    assert temporaries(root) == []
    assert store.open_count("sub/b.robot") == 0


# ---------------------------------------------------------------- paths never leave the root

TRAVERSALS = [
    "..",
    "../x",
    "../programs/a.robot",
    "/etc/passwd",
    "sub/../a.robot",
    "sub/./b.robot",
    "sub//b.robot",
    "sub/",
    "./a.robot",
    "sub\\b.robot",
    f"{TEMP_PREFIX}x",
]


@pytest.mark.parametrize("relpath", TRAVERSALS)
def test_traversal_in_paths_is_refused(store: FileStore, root: Path, relpath: str) -> None:
    before_outside = sorted(p.name for p in root.parent.iterdir())
    before = snapshot(root)
    for call in (
        lambda: store.open(S1, relpath, R | W),
        lambda: store.entry(relpath),
        lambda: store.entries(relpath),
        lambda: store.delete(relpath),
        lambda: store.create_file(S1, relpath, "x", False),
        lambda: store.create_directory(relpath, "x"),
        lambda: store.move_or_copy(relpath, "", True, "x"),
        lambda: store.move_or_copy("a.robot", relpath, True, "x"),
    ):
        with pytest.raises(CallError) as exc:
            call()
        assert exc.value.status == "BadInvalidArgument"
    assert snapshot(root) == before
    assert sorted(p.name for p in root.parent.iterdir()) == before_outside


def test_symlinks_are_never_followed(store: FileStore, root: Path, tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret").write_bytes(b"secret")
    (root / "out").symlink_to(outside)
    (root / "sec").symlink_to(outside / "secret")
    for call in (
        lambda: store.open(S1, "sec", R),
        lambda: store.open(S1, "out/secret", R),
        lambda: store.create_file(S1, "out", "x", False),
        lambda: store.move_or_copy("a.robot", "out", False, None),
        lambda: store.delete("out/secret"),
    ):
        with pytest.raises(CallError) as exc:
            call()
        assert exc.value.status == "BadNotFound"
    assert sorted(p.name for p in outside.iterdir()) == ["secret"]
    assert (root / "a.robot").exists()


# ---------------------------------------------------------------- change listeners


def test_open_close_and_commit_notify_changed(store: FileStore, changes: list[Change]) -> None:
    h = store.open(S1, "a.robot", W)
    store.write(S1, h, b"x")
    store.close(S1, h)
    store.close_session(S1)  # nothing open: no change
    assert changes == [Change("changed", "a.robot", False)] * 2


def test_failing_listener_does_not_break_the_store(store: FileStore, root: Path, changes: list[Change]) -> None:
    def broken(change: Change) -> None:
        raise RuntimeError("binding bug")

    store.listeners.insert(0, broken)
    store.create_directory("", "d")
    assert (root / "d").is_dir()
    assert changes == [Change("added", "d", True)]
