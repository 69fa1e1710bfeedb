"""stdr-data against a local HTTP server on 127.0.0.1 serving fixture archives: a download that
succeeds, one cut off and resumed, a corrupted archive, a wrong layout, a path-traversal member,
sources tried in order, the lock file, and the 400x400 preparation."""
import io
import json
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest
from PIL import Image

from stdr.cli.data import main as stdr_data, prepare_dnerf
from stdr.data import fetch
from stdr.data.load import verify_scene


def _png(size=8, color=(255, 0, 0, 255)) -> bytes:
    b = io.BytesIO()
    Image.new("RGBA", (size, size), color).save(b, format="PNG")
    return b.getvalue()


def _dnerf_scene(prefix: str, z: zipfile.ZipFile, size=8, missing_val=False) -> None:
    for split in ("train", "val", "test"):
        frames = [{"file_path": f"./{split}/r_{i:03d}", "time": i / 2, "transform_matrix": np.eye(4).tolist()}
                  for i in range(3)]
        if missing_val and split == "val":
            frames[0]["file_path"] = "./val/nope"
        z.writestr(f"{prefix}transforms_{split}.json", json.dumps({"camera_angle_x": 0.69, "frames": frames}))
        for i in range(3):
            z.writestr(f"{prefix}{split}/r_{i:03d}.png", _png(size))


def _zip(build) -> bytes:
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", zipfile.ZIP_DEFLATED) as z:
        build(z)
    return b.getvalue()


DNERF = _zip(lambda z: (_dnerf_scene("data/standup/", z), _dnerf_scene("data/lego/", z)))


class Server:
    """Files by path; `cut[path] = n` serves only the first n bytes once (announcing the full
    length), as a dropped connection would; Range requests are honoured; every request's Range
    header is recorded."""

    def __init__(self):
        self.files: dict[str, bytes] = {}
        self.cut: dict[str, int] = {}
        self.ranges: list = []
        srv = self

        class H(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_GET(self):
                data = srv.files.get(self.path)
                srv.ranges.append((self.path, self.headers.get("Range")))
                if data is None:
                    self.send_error(404)
                    return
                start = 0
                rng = self.headers.get("Range")
                if rng:
                    start = int(rng.split("=")[1].split("-")[0])
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                else:
                    self.send_response(200)
                body = data[start:]
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                n = srv.cut.pop(self.path, None)
                self.wfile.write(body if n is None else body[:n])
                if n is not None:
                    self.close_connection = True

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), H)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()


@pytest.fixture
def server(monkeypatch):
    monkeypatch.setenv("STDR_DATA_QUIET", "1")
    s = Server()
    yield s
    s.httpd.shutdown()


def test_a_download_is_checked_unpacked_and_verified(tmp_path, server, capsys):
    server.files["/data.zip"] = DNERF
    dest = tmp_path / "dnerf"
    stdr_data(["download", "dnerf", "--dest", str(dest), "--urls", f"{server.url}/missing.zip",
               f"{server.url}/data.zip", "--scenes", "standup"])
    out = capsys.readouterr().out
    assert sorted(p.name for p in dest.iterdir() if not p.name.startswith(".")) == ["standup",
                                                                                      "stdr-data.lock.json"]
    assert "standup: dnerf layout ok (9 images)" in out and "SHA-256 recorded" in out
    lock = json.loads((dest / "stdr-data.lock.json").read_text())["dnerf-data.zip"]
    assert lock["size"] == len(DNERF) and lock["url"].endswith("/data.zip")  # the second source, after a 404
    assert not (dest / ".downloads" / "dnerf-data.zip").exists()  # removed once unpacked
    assert not [p for p in dest.iterdir() if p.name.startswith(".stdr-data-")]  # no temporary folder left
    # the same archive again, into another folder that shares the lock: it matches
    (tmp_path / "again").mkdir()
    (tmp_path / "again" / "stdr-data.lock.json").write_text((dest / "stdr-data.lock.json").read_text())
    stdr_data(["download", "dnerf", "--dest", str(tmp_path / "again"), "--urls", f"{server.url}/data.zip"])
    assert "SHA-256 matches" in capsys.readouterr().out
    assert (tmp_path / "again" / "lego").is_dir() and (tmp_path / "again" / "standup").is_dir()


def test_a_cut_transfer_resumes_with_a_range_request(tmp_path, server):
    server.files["/data.zip"] = DNERF
    server.cut["/data.zip"] = len(DNERF) // 3
    dest = tmp_path / "a.zip"
    with pytest.raises(fetch.DataError, match="resume"):
        fetch.download([f"{server.url}/data.zip"], dest)
    part = tmp_path / "a.zip.part"
    assert part.stat().st_size == len(DNERF) // 3 and not dest.exists()
    fetch.download([f"{server.url}/data.zip"], dest)
    assert dest.read_bytes() == DNERF and not part.exists()
    assert server.ranges[-1] == ("/data.zip", f"bytes={len(DNERF) // 3}-")


def test_a_corrupted_archive_and_a_changed_source_are_refused(tmp_path):
    bad = bytearray(DNERF)
    with zipfile.ZipFile(io.BytesIO(DNERF)) as z:  # flip a byte inside the first member's data
        info = z.infolist()[0]
    bad[info.header_offset + 30 + len(info.filename) + 2] ^= 0xFF
    (tmp_path / "bad.zip").write_bytes(bytes(bad))
    with pytest.raises(fetch.DataError, match="fails its CRC check|not a readable zip"):
        fetch.check_archive(tmp_path / "bad.zip")
    (tmp_path / "trunc.zip").write_bytes(DNERF[: len(DNERF) // 2])
    with pytest.raises(fetch.DataError, match="not a readable zip archive"):
        fetch.check_archive(tmp_path / "trunc.zip")
    # through the command: the damaged archive is refused before the lock records it
    with pytest.raises(SystemExit):
        stdr_data(["download", "dnerf", "--dest", str(tmp_path / "c"), "--archive", str(tmp_path / "trunc.zip")])
    assert not (tmp_path / "c" / "stdr-data.lock.json").exists()
    lock = fetch.Lock(tmp_path / "d")
    (tmp_path / "good.zip").write_bytes(DNERF)
    state, entry = lock.check("x.zip", tmp_path / "good.zip", "u")
    assert state == "recorded" and not lock.path.exists()  # checking writes nothing
    lock.record("x.zip", entry)
    assert fetch.Lock(tmp_path / "d").check("x.zip", tmp_path / "good.zip", "u")[0] == "matches"
    with pytest.raises(fetch.DataError, match="recorded .* bytes, SHA-256"):
        fetch.Lock(tmp_path / "d").check("x.zip", tmp_path / "bad.zip", "u")


def test_a_wrong_layout_is_reported_by_name_and_nothing_is_unpacked(tmp_path, capsys):
    (tmp_path / "w.zip").write_bytes(_zip(lambda z: (_dnerf_scene("data/standup/", z),
                                                    _dnerf_scene("data/lego/", z, missing_val=True))))
    with pytest.raises(SystemExit) as e:
        stdr_data(["download", "dnerf", "--dest", str(tmp_path / "d"), "--archive", str(tmp_path / "w.zip")])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "scene lego: lego is not a complete D-NeRF scene" in err and "./val/nope' not found" in err
    assert "nothing was unpacked" in err and len(err.strip().splitlines()) == 1
    # not even the good scene, and no lock: an archive is recorded only once it unpacked and passed
    assert [p.name for p in (tmp_path / "d").iterdir()] == []
    (tmp_path / "n.zip").write_bytes(_zip(lambda z: z.writestr("scene/dataset.json", "{}")))
    with pytest.raises(fetch.DataError, match="missing metadata.json, scene.json"):
        fetch.safe_extract(tmp_path / "n.zip", tmp_path / "e", check=lambda f: verify_scene(f, "nerfies"))


@pytest.mark.parametrize("member", ["../evil.txt", "/tmp/evil.txt", "data/../../evil.txt", "link"])
def test_a_member_that_leaves_the_destination_is_refused(tmp_path, member):
    def build(z):
        _dnerf_scene("data/standup/", z)
        if member == "link":
            info = zipfile.ZipInfo("data/standup/link")
            info.external_attr = (0o120777 << 16)  # a symbolic link
            z.writestr(info, "../../../etc/passwd")
        else:
            z.writestr(member, "x")
    (tmp_path / "evil.zip").write_bytes(_zip(build))
    dest = tmp_path / "d"
    with pytest.raises(fetch.DataError, match="refusing to unpack"):
        fetch.safe_extract(tmp_path / "evil.zip", dest)
    assert not (tmp_path / "evil.txt").exists() and list(dest.iterdir()) == []


def test_the_top_level_folder_is_detected_and_an_existing_scene_is_kept(tmp_path):
    one = _zip(lambda z: _dnerf_scene("vrig-broom/", z))  # a per-scene archive: its one folder is the scene
    (tmp_path / "one.zip").write_bytes(one)
    assert [p.name for p in fetch.safe_extract(tmp_path / "one.zip", tmp_path / "d")] == ["vrig-broom"]
    with pytest.raises(fetch.DataError, match="exists already"):
        fetch.safe_extract(tmp_path / "one.zip", tmp_path / "d")
    flat = _zip(lambda z: _dnerf_scene("", z))  # the scene's files at the top
    (tmp_path / "flat.zip").write_bytes(flat)
    assert [p.name for p in fetch.safe_extract(tmp_path / "flat.zip", tmp_path / "e")] == ["flat"]


def test_prepare_makes_400_copies_with_premultiplied_alpha(tmp_path):
    (tmp_path / "s.zip").write_bytes(_zip(lambda z: _dnerf_scene("data/standup/", z)))
    fetch.safe_extract(tmp_path / "s.zip", tmp_path / "src")
    img = tmp_path / "src" / "standup" / "train" / "r_000.png"
    a = np.zeros((8, 8, 4), np.uint8)
    a[:, :4] = (255, 0, 0, 255)  # opaque red on the left, transparent green on the right
    a[:, 4:] = (0, 255, 0, 0)
    Image.fromarray(a, "RGBA").save(img)
    [out] = prepare_dnerf(tmp_path / "src" / "standup", tmp_path / "out", size=4)
    got = np.asarray(Image.open(out / "train" / "r_000.png").convert("RGBA")).astype(int)
    assert got.shape == (4, 4, 4)
    seen = got[..., 3] > 0
    assert seen.any() and (got[seen][:, 1] <= 2).all()  # no green bleeds into visible pixels
    assert json.loads((out / "transforms_train.json").read_text()) == json.loads(
        (tmp_path / "src" / "standup" / "transforms_train.json").read_text())
    assert verify_scene(out, "dnerf") == 9


def test_list_names_every_dataset(capsys):
    stdr_data(["list"])
    out = capsys.readouterr().out
    for name in ("dnerf", "nerfds", "hypernerf"):
        assert f"{name} " in out
    assert "vrig_broom" in out and "huggingface.co" in out


def test_an_archive_without_a_scene_is_an_error_and_is_kept_unrecorded(tmp_path, server, capsys):
    """A valid zip that holds no scene: exit 2, nothing placed, no lock entry, the download kept."""
    server.files["/data.zip"] = _zip(lambda z: z.writestr("readme/notes.txt", "hello"))
    dest = tmp_path / "dnerf"
    with pytest.raises(SystemExit) as e:
        stdr_data(["download", "dnerf", "--dest", str(dest), "--urls", f"{server.url}/data.zip"])
    assert e.value.code == 2
    assert "holds no scene folder" in capsys.readouterr().err
    assert not (dest / "stdr-data.lock.json").exists()
    assert (dest / ".downloads" / "dnerf-data.zip").is_file()  # not deleted: the user may want to look at it
    assert not [p for p in dest.iterdir() if not p.name.startswith(".")]


def test_a_part_the_server_calls_complete_is_checked_and_kept(tmp_path, server):
    """A .part that already holds the whole file gets 416 from the server: kept after its check."""
    server.files["/data.zip"] = DNERF
    dest = tmp_path / "a.zip"
    (tmp_path / "a.zip.part").write_bytes(DNERF)
    real = server.httpd.RequestHandlerClass.do_GET

    def do_get(h):
        rng = h.headers.get("Range")
        if rng and int(rng.split("=")[1].split("-")[0]) >= len(DNERF):  # as servers do: nothing left to send
            h.send_response(416)
            h.send_header("Content-Range", f"bytes */{len(DNERF)}")
            h.send_header("Content-Length", "0")
            h.end_headers()
            return
        real(h)
    server.httpd.RequestHandlerClass.do_GET = do_get
    fetch.download([f"{server.url}/data.zip"], dest, verify=fetch.check_archive)
    assert dest.read_bytes() == DNERF and not (tmp_path / "a.zip.part").exists()
    # a .part longer than the file (another file's): 416 with another total, so it starts over
    (tmp_path / "b.zip.part").write_bytes(DNERF + b"x" * 10)
    fetch.download([f"{server.url}/data.zip"], tmp_path / "b.zip", verify=fetch.check_archive)
    assert (tmp_path / "b.zip").read_bytes() == DNERF


def test_a_resume_that_does_not_continue_the_part_starts_over(tmp_path, server):
    """The server answers 206 from another offset than the .part's end: the .part is not merged."""
    server.files["/data.zip"] = DNERF
    real = server.httpd.RequestHandlerClass.do_GET

    def do_get(h):
        if h.headers.get("Range"):
            body = DNERF[5:]
            h.send_response(206)
            h.send_header("Content-Range", f"bytes 5-{len(DNERF) - 1}/{len(DNERF)}")
            h.send_header("Content-Length", str(len(body)))
            h.end_headers()
            h.wfile.write(body)
            return
        real(h)
    server.httpd.RequestHandlerClass.do_GET = do_get
    (tmp_path / "a.zip.part").write_bytes(DNERF[:100])
    fetch.download([f"{server.url}/data.zip"], tmp_path / "a.zip", verify=fetch.check_archive)
    assert (tmp_path / "a.zip").read_bytes() == DNERF


def test_a_body_of_unknown_length_is_kept_only_when_its_check_passes(tmp_path, server):
    """No Content-Length: a cut body is deleted, not moved into place; a whole one is kept."""
    def serve(data):
        def do_get(h):
            h.send_response(200)
            h.end_headers()  # no Content-Length: the body ends when the connection closes
            h.wfile.write(data)
            h.close_connection = True
        server.httpd.RequestHandlerClass.do_GET = do_get
    serve(DNERF[: len(DNERF) // 2])
    with pytest.raises(fetch.DataError, match="fails its check"):
        fetch.download([f"{server.url}/data.zip"], tmp_path / "a.zip", verify=fetch.check_archive)
    assert not (tmp_path / "a.zip").exists() and not (tmp_path / "a.zip.part").exists()
    with pytest.raises(fetch.DataError, match="nothing to check it against"):
        fetch.download([f"{server.url}/data.zip"], tmp_path / "b.zip")
    assert not (tmp_path / "b.zip").exists()
    serve(DNERF)
    fetch.download([f"{server.url}/data.zip"], tmp_path / "c.zip", verify=fetch.check_archive)
    assert (tmp_path / "c.zip").read_bytes() == DNERF


def _tar(path, members):
    """members: (name, bytes) for a file, (name, None) for a folder, (name, 'link') for a symlink."""
    import tarfile
    with tarfile.open(path, "w:xz") as tar:
        for name, data in members:
            info = tarfile.TarInfo(name)
            if data is None:
                info.type = tarfile.DIRTYPE
                tar.addfile(info)
            elif data == "link":
                info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
                tar.addfile(info)
            else:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))


def test_tar_extraction_is_all_or_nothing_and_takes_folder_entries(tmp_path):
    """A bad member after good ones leaves the destination as it was and no temporary folder;
    `tar -cJf` archives (folder entries first) unpack; files replace files of the same name."""
    dest = tmp_path / "study"
    dest.mkdir()
    (dest / "README.md").write_text("kept")
    for bad in (("../escape.txt", b"x"), ("/abs.txt", b"x"), ("records/link", "link")):
        _tar(tmp_path / "bad.tar.xz", [("records", None), ("records/a.json", b"1"), bad])
        with pytest.raises(fetch.DataError, match="refused, nothing was unpacked"):
            fetch.extract_tar(tmp_path / "bad.tar.xz", dest)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.tar.xz", "study"], bad  # no temp folder
        assert sorted(p.name for p in dest.iterdir()) == ["README.md"], bad
    _tar(tmp_path / "ok.tar.xz", [("records", None), ("records/run1", None), ("records/run1/a.json", b"1"),
                                  ("README.md", b"new")])
    assert fetch.extract_tar(tmp_path / "ok.tar.xz", dest) == ["README.md", "records/run1/a.json"]
    assert (dest / "records" / "run1" / "a.json").read_bytes() == b"1" and (dest / "README.md").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.tar.xz", "ok.tar.xz", "study"]
    # a rule for the names: the GPU table's <run id>/<file>
    with pytest.raises(fetch.DataError, match="is not <run id>/<file>"):
        fetch.extract_tar(tmp_path / "ok.tar.xz", tmp_path / "runs", member_ok=lambda n: n.count("/") == 1,
                          what="<run id>/<file>")
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())
