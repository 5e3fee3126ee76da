"""annotate.store and annotate.schema: atomic saves, restore after a kill, version conflicts,
strict validation that never overwrites a bad file, confinement and upload checks."""
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from annotate import schema as S
from annotate.store import ConflictError, Project, StoreError, check_image_bytes
from racklay.atomic import encode_png


def _png(w=64, h=48):
    return encode_png(np.full((h, w, 3), 120, np.uint8))


@pytest.fixture
def proj(tmp_path):
    (tmp_path / "a.png").write_bytes(_png())
    (tmp_path / "b.png").write_bytes(_png())
    return Project(tmp_path)


def test_new_project_and_progress(proj):
    assert (proj.root / "project.json").exists()
    assert proj.images() == ["a.png", "b.png"]
    ann = proj.load("a.png")
    assert ann["status"] == "todo" and ann["version"] == 0 and ann["image_size"] == [64, 48]
    ann["status"] = "done"
    proj.save(ann)
    assert proj.progress() == (1, 2)
    assert proj.resume_image() == "b.png"


def test_save_bumps_version_and_restores(proj):
    ann = proj.load("a.png")
    ann["rack"]["corners"] = [[1, 2], [30, 2]]
    ann["status"] = "in progress"
    saved = proj.save(ann, user="ana")
    assert saved["version"] == 1
    again = Project(proj.root).load("a.png")  # a new server process would do exactly this
    assert again["rack"]["corners"] == [[1, 2], [30, 2]] and again["updated_by"] == "ana"
    assert proj.resume_image() == "a.png"
    assert not list((proj.root / "annotations").glob(".*.tmp"))


def test_concurrent_edit_refused_with_message(proj):
    one = proj.load("a.png")
    two = proj.load("a.png")  # a second labeller opens the same image
    one["shelves"].append({"id": 0, "point": [5, 5]})
    proj.save(one, user="ana")
    two["shelves"].append({"id": 0, "point": [9, 9]})
    with pytest.raises(ConflictError, match=r"ana changed this image meanwhile \(version 1 on disk, your edit started from version 0\)"):
        proj.save(two, user="ben")
    assert proj.load("a.png")["shelves"][0]["point"] == [5, 5]


def test_corrupted_json_clear_error_and_not_overwritten(proj):
    p = proj.annotation_path("a.png")
    p.parent.mkdir(exist_ok=True)
    p.write_text('{"schema_version": 1, "image": "a.png",')
    with pytest.raises(S.SchemaError, match=r"a\.png\.json: not valid JSON"):
        proj.load("a.png")
    fresh = S.new_annotation("a.png", 64, 48)
    with pytest.raises(S.SchemaError):
        proj.save(fresh)
    assert p.read_text() == '{"schema_version": 1, "image": "a.png",'
    assert proj.statuses()["a.png"] == "invalid"


@pytest.mark.parametrize("edit, field", [
    (lambda d: d.update(status="finished"), "status"),
    (lambda d: d["rack"].update(width=-2), "rack.width"),
    (lambda d: d.update(schema_version=99), "schema_version"),
    (lambda d: d["boxes"].append({"id": 0, "p0": [0, 0], "p1": ["x", 0]}), r"boxes\[0\].p1\[0\]"),
    (lambda d: d.update(colour="red"), "colour"),
    (lambda d: d.update(imported={"top": "../../etc/passwd", "front": None}), "imported.top"),
])
def test_strict_validation_names_file_and_field(proj, edit, field):
    d = S.new_annotation("a.png", 64, 48)
    edit(d)
    p = proj.annotation_path("a.png")
    p.parent.mkdir(exist_ok=True)
    p.write_text(json.dumps(d))
    with pytest.raises(S.SchemaError, match=rf"a\.png\.json: field '{field}'"):
        proj.load("a.png")


def test_settings_validation(tmp_path):
    s = S.default_settings()
    assert s["presets"][0]["name"] == "boltless 2.0 × 2.0 × 0.6 m"
    s["D"] = 511
    (tmp_path / "project.json").write_text(json.dumps(s))
    with pytest.raises(S.SchemaError, match=r"project\.json: field 'D': must be even"):
        Project(tmp_path)


def test_paths_confined(proj):
    for bad in ("../x.png", "/etc/passwd", "sub/a.png", ".hidden.png", "a.png/../../b.png"):
        with pytest.raises(ValueError):
            proj.image_path(bad)
    with pytest.raises(ValueError):
        proj.project_file("../outside.npy")


def test_uploads_checked(proj):
    assert proj.add_image("../../evil name.PNG", _png()) == "evil_name.png"
    assert (proj.root / "evil_name.png").exists()
    with pytest.raises(StoreError, match="not a readable"):
        proj.add_image("x.png", b"GIF89a not really")
    with pytest.raises(StoreError, match="already in the project"):
        proj.add_image("a.png", _png())
    # a decompression bomb: a tiny PNG declaring 20000 x 20000 pixels is refused from its header
    import struct
    import zlib
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xffffffff)
    raw = zlib.compress(b"\0" * (20000 + 1) * 64)  # only 64 rows of data: the header is what counts
    bomb = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 20000, 20000, 8, 0, 0, 0, 0)) + chunk(b"IDAT", raw) + chunk(b"IEND", b"")
    with pytest.raises(StoreError, match="decompression bomb"):
        check_image_bytes(bomb, "bomb.png")
    with pytest.raises(StoreError, match="empty"):
        check_image_bytes(b"", "e.png")


def test_restore_after_kill(proj):
    """A writer killed with SIGKILL in the middle of saving leaves a valid file at its last state."""
    script = textwrap.dedent(f"""
        import sys
        from annotate.store import Project
        p = Project({str(proj.root)!r})
        ann = p.load("a.png")
        i = 0
        while True:
            ann["shelves"] = [{{"id": k, "point": [k, i]}} for k in range(50)]
            ann = p.save(ann)
            i += 1
            if i == 5:
                print("saving", flush=True)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "saving"
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    ann = proj.load("a.png")  # valid JSON, consistent content
    assert ann["version"] >= 5
    assert len(ann["shelves"]) == 50 and len({s["point"][1] for s in ann["shelves"]}) == 1
    ann["status"] = "in progress"
    assert proj.save(ann)["version"] == ann["version"] + 1


def test_settings_save_with_lock_and_version_check(proj):
    """project.json is saved like an annotation: a session whose settings are stale (another one
    saved meanwhile) is refused and overwrites nothing; a save waits for the lock."""
    import fcntl
    import threading

    a, b = Project(proj.root), Project(proj.root)
    saved = a.save_settings(dict(a.settings, extent=6.0))
    assert saved["version"] == 1 and S.load_settings(proj.root / "project.json")["extent"] == 6.0
    with pytest.raises(ConflictError, match=r"project\.json: not saved - the project settings changed "
                                            r"meanwhile \(version 1 on disk, your edit started from version 0\)"):
        b.save_settings(dict(b.settings, R=2))
    on_disk = S.load_settings(proj.root / "project.json")
    assert (on_disk["R"], on_disk["extent"], on_disk["version"]) == (4, 6.0, 1)
    # a reloaded session saves; and a save waits while another process holds the lock
    c = Project(proj.root)
    fd = os.open(proj.root, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)
    t = threading.Thread(target=c.save_settings, args=(dict(c.settings, R=2),))
    t.start()
    t.join(0.5)
    assert t.is_alive() and S.load_settings(proj.root / "project.json")["R"] == 4
    fcntl.flock(fd, fcntl.LOCK_UN)
    os.close(fd)
    t.join(30)
    assert S.load_settings(proj.root / "project.json")["R"] == 2 and c.settings["version"] == 2
