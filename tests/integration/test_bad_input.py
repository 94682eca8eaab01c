"""Bad command lines and files, for every subcommand, as a user meets them: exit code 2 and
one line ``vistrack <sub>: error: ...`` on stderr that names the flag, file or field, the
value and what is allowed; no traceback, no library's own log lines, nothing started.

Each case runs the real command in a process of its own (C libraries write to the process's
stderr, which only a process of its own shows) and compares the whole of stderr with the
expected line. The processes are forked from one that has imported vistrack once
(tests/forkcli.py); :data:`FRESH` cases start a new interpreter, start-up and teardown
included.
Paths in the expected lines are written ``{d}``: the folder of the bad files.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
from forkcli import vistrack as run_vistrack

pytestmark = pytest.mark.integration

NS = "--no-multicast-scouting"
# Zenoh flags never reach a network: a case either fails before the session opens, or is a
# bug that the timeout turns into a failure.
TIMEOUT_S = 30


@pytest.fixture(scope="module")
def d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of bad inputs (and one good recording and video to cut)."""
    d = tmp_path_factory.mktemp("bad")
    (d / "empty").mkdir()
    (d / "mixed").mkdir()
    cv2.imwrite(str(d / "mixed" / "a.png"), np.full((64, 64), 128, np.uint8))
    (d / "mixed" / "b.png").write_bytes(b"not a png")
    (d / "junk.mp4").write_bytes(bytes(range(256)) * 20)
    # damaged so that the C libraries under OpenCV complain on stderr (libpng's "Read
    # Error"; FFmpeg's and OpenCV's AVI readers' header messages)
    png = cv2.imencode(".png", rng_noise((200, 300)))[1].tobytes()
    (d / "trunc.png").write_bytes(png[:len(png) // 2])
    riff = d / "riff.avi"  # an AVI header, then no AVI
    riff.write_bytes(b"RIFF\x00\x10\x00\x00AVI " + bytes(range(256)) * 4)
    (d / "badfirst").mkdir()  # its first image is no image
    (d / "badfirst" / "a.png").write_bytes(b"not a png")
    cv2.imwrite(str(d / "badfirst" / "b.png"), np.full((64, 64), 128, np.uint8))
    (d / "cutjpg").mkdir()
    rng = np.random.default_rng(0)
    for name in ("a.jpg", "b.jpg"):
        cv2.imwrite(str(d / "cutjpg" / name), rng.integers(0, 256, (64, 64), dtype=np.uint8))
    jpeg = (d / "cutjpg" / "b.jpg").read_bytes()
    (d / "cutjpg" / "b.jpg").write_bytes(jpeg[:len(jpeg) // 2])
    video = d / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 64))
    rng = np.random.default_rng(0)
    for _ in range(10):
        writer.write(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8))
    writer.release()
    data = video.read_bytes()
    (d / "cut.avi").write_bytes(data[:len(data) // 3])
    cv2.imwrite(str(d / "wide.png"), np.zeros((10, 5000), np.uint8))
    (d / "bad.json5").write_text("{ mode: 'peer', ")
    header = msgpack.packb({"format": "vistrack-record", "version": 1, "robot": "robot",
                            "keys": ["vistrack/robot/**"], "start_ns": 1})
    (d / "garbage.rec").write_bytes(bytes(range(200)))
    (d / "badkey.rec").write_bytes(header + msgpack.packb(
        {"t_ns": 1, "key": "vistrack/robot//frame", "payload": b"x"}))
    return d


def vistrack(*args: str, fresh: bool = False) -> subprocess.CompletedProcess:
    return run_vistrack(*args, timeout=TIMEOUT_S, fresh=fresh)


def rng_noise(shape: tuple[int, int]) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)


def check(run: subprocess.CompletedProcess, sub: str, message: str) -> None:
    assert (run.returncode, run.stderr) == (2, f"vistrack {sub}: error: {message}\n"), \
        run.stderr


# (argv, expected message) per subcommand; {d} is the folder of bad inputs
CASES = {
    "track": [
        (["--max-features", "1e9"], "--max-features '1e9' is not an integer: allowed 1..2000"),
        (["--thres-percent", "inf"], "--thres-percent inf is out of range: allowed 0.1..5"),
        (["--resize", "4x4"], "--resize 4x4 is out of range: width and height must be 8..8192"),
        (["{d}/mixed"], "{d}/mixed/b.png: not a readable image"),
        (["{d}/junk.mp4"], "{d}/junk.mp4: not a readable video"),
        # one line of ours, without the libraries' own (which used to come first)
        (["{d}/trunc.png"], "{d}/trunc.png: not a readable image"),
        (["{d}/riff.avi"], "{d}/riff.avi: not a readable video"),
        (["{d}/cutjpg"], "{d}/cutjpg/b.jpg: damaged image: the JPEG data ends before the image "
                         "does (cut short?)"),
        (["{d}/cut.avi"], "{d}/cut.avi: the video ends after 3 of the 10 frames its header "
                          "announces (cut short or damaged)"),
        ([""], "'' is not a file or folder: give a video, a folder of images, a glob or image "
               "files"),
        (["--bogus"], "unrecognized arguments: --bogus (see vistrack track --help)"),
    ],
    "tune": [
        (["--seed", "-1"], "--seed -1 is out of range: allowed 0..9223372036854775807"),
        (["--step", "50"], "--step 50 is out of range: allowed 1..10"),
        (["--tolerance", "inf"], "--tolerance inf is out of range: allowed 0..100"),
    ],
    "camera": [
        (["--fps", "1e9", NS], "--fps 1e9 is out of range: allowed 0 or 0.1..1000"),
        (["--fps", "1e-10", NS], "--fps 1e-10 is out of range: allowed 0 or 0.1..1000"),
        # the simulator's own flags were ignored in silence with another source
        (["--source", "builtin", "--texture", "/nonexistent", "--seed", "3", NS],
         "--texture, --seed: for --source sim only (the robot simulator), not builtin"),
        (["--source", "device:-1", NS],
         "'device:-1': device index -1 is out of range: allowed 0..99"),
        (["--source", "device:x", NS],
         "'device:x': the device index must be an integer 0..99, e.g. device:0"),
        (["--source", "file:", NS],
         "--source 'file:' names no file: give file:PATH (a video, an image folder or a glob)"),
        (["--source", "file:{d}/junk.mp4", NS], "{d}/junk.mp4: not a readable video"),
        (["--source", "file:{d}/mixed", NS], "{d}/mixed/b.png: not a readable image"),
        (["--source", "file:{d}/wide.png", NS], "frames are 5000x10: a camera/frame carries at "
                                                "most 4096 px a side; give --size to scale them"),
        (["--size", "5000x5000", NS],
         "--size 5000x5000 is out of range: width and height must be 8..4096"),
        (["--source", "sim", "--size", "8x8", NS],
         "--size 8x8 is out of range: width and height must be 16..4096"),
        (["--source", "sim", "--noise", "nan", NS], "--noise nan is out of range: allowed 0..100"),
        (["--source", "sim", "--seed", "-1", NS],
         "--seed -1 is out of range: allowed 0..9223372036854775807"),
        (["--source", "sim:nowhere", NS], "--source sim:nowhere: 'nowhere' is neither a "
         "built-in scenario (allowed: default, sideways, approach, steps, still, lighting) nor "
         "an existing YAML file"),
        (["-l", "tcp/1.2.3", NS], "-l/--listen 'tcp/1.2.3' is not a Zenoh endpoint: expected "
                                  "tcp/<host>:<port> with a port 0..65535, e.g. "
                                  "tcp/127.0.0.1:7447"),
        (["-c", "{d}/bad.json5", NS], "zenoh config file {d}/bad.json5: line 1, column 17: "
                                      "expected identifier or string"),
    ],
    "preprocessing": [
        (["--search-size", "1e3", NS], "--search-size '1e3' is not an integer: allowed 2..128"),
    ],
    "motion-estimation": [
        (["-e", "tcp/127.0.0.1:99999", NS], "-e/--connect 'tcp/127.0.0.1:99999' is not a Zenoh "
         "endpoint: expected tcp/<host>:<port> with a port 0..65535, e.g. tcp/127.0.0.1:7447"),
    ],
    "auto-tuner": [
        (["--buffer", "1e9", NS], "--buffer '1e9' is not an integer: allowed 2..1000"),
        (["--min-interval", "inf", NS], "--min-interval inf is out of range: allowed 0..86400"),
    ],
    "fuzzy-controller": [
        (["--image-width", "0", NS], "--image-width 0 is out of range: allowed 8..4096"),
        (["--image-width", "nan", NS], "--image-width nan is out of range: allowed 8..4096"),
        (["--stale-after", "inf", NS], "--stale-after inf is out of range: allowed 0 < S <= 10"),
        (["--x-ref", "nan", NS], "--x-ref nan is out of range: allowed 0..100000"),
        (["--min-npi", "99999999999", NS],
         "--min-npi 99999999999 is out of range: allowed 0..10000"),
    ],
    "echo": [
        (["camera/frame", "--timeout", "nan", NS],
         "--timeout nan is out of range: allowed 0 < S <= 1000000 s"),
        (["camera/frame", "--timeout", "inf", NS],
         "--timeout inf is out of range: allowed 0 < S <= 1000000 s"),
        (["camera/frame", "--count", "0", NS], "--count 0 is out of range: allowed 1..1000000000"),
    ],
    "hz": [
        (["camera/frame", "--duration", "nan", NS],
         "--duration nan is out of range: allowed 0 < S <= 1000000 s"),
        (["camera/frame", "--window", "100000000000", NS],
         "--window 100000000000 is out of range: allowed 2..100000"),
    ],
    "status": [
        (["--timeout", "inf", NS], "--timeout inf is out of range: allowed 0 < S <= 3600 s"),
        (["--timeout", "nan", NS], "--timeout nan is out of range: allowed 0 < S <= 3600 s"),
    ],
    "params": [
        (["get", "--timeout", "1e300", NS],
         "--timeout 1e300 is out of range: allowed 0 < S <= 3600 s"),
        (["set", "search_size=21", "--timeout", "nan", NS],
         "--timeout nan is out of range: allowed 0 < S <= 3600 s"),
        (["set", "search_size=nan", NS], "search_size=nan must be an integer in 2..128"),
    ],
    "record": [
        (["{d}/out.rec", "--duration", "nan", NS],
         "--duration nan is out of range: allowed 0 < S <= 1000000 s"),
    ],
    "replay": [
        (["{d}/garbage.rec", NS], "{d}/garbage.rec at byte offset 0: not a vistrack recording "
                                  "(no vistrack-record header)"),
        (["{d}/garbage.rec", "--wait", "nan", NS],
         "--wait nan is out of range: allowed 0..3600 s"),
    ],
    "router": [
        (["-c", "{d}/bad.json5"], "zenoh config file {d}/bad.json5: line 1, column 17: "
                                  "expected identifier or string"),
        (["-l", "tcp/127.0.0.1:99999", NS], "-l/--listen 'tcp/127.0.0.1:99999' is not a Zenoh "
         "endpoint: expected tcp/<host>:<port> with a port 0..65535, e.g. tcp/127.0.0.1:7447"),
    ],
    "certs": [
        (["ca", "--dir", "{d}/ca", "--days", "0"], "--days 0 is out of range: allowed 1..36500"),
        (["ca", "--dir", "{d}/ca", "--name", ""],
         "--name '' is 0 characters long: a common name has 1 to 64"),
    ],
    "up": [
        # the camera's own flag was named, not the --camera the user typed
        (["--camera", "file:", "-l", "tcp/127.0.0.1:1"],
         "--camera 'file:' names no file: give file:PATH (a video, an image folder or a glob)"),
        # every service tried to listen on 7447, all but one found it taken
        (["-m", "router"], "-m router: the services cannot all be routers (the embedded "
                           "router, or -e ROUTER, routes for them): allowed peer (the default) "
                           "or client"),
        (["-l", "tcp/127.0.0.1:0"], "-l tcp/127.0.0.1:0: the services connect to the "
                                    "router's endpoints, so give it a port of its own, not 0"),
        (["--fps", "nan", "-l", "tcp/127.0.0.1:1"],
         "--fps nan is out of range: allowed 0 or 0.1..1000"),
        # the launch file's ready_timeout range: 0.05 was taken, then "not ready after 0.05 s"
        (["--ready-timeout", "0.05"], "--ready-timeout 0.05 is out of range: allowed 0.1..3600 s"),
        # up's own flag, with the camera's range (argparse's 'invalid float value' named none)
        (["--fps", "abc", "-l", "tcp/127.0.0.1:1"],
         "--fps 'abc' is not a number: allowed 0 or 0.1..1000"),
        (["--size", "", "-l", "tcp/127.0.0.1:1"],  # was: native size, without a word
         "--size '' is not WIDTHxHEIGHT, e.g. 256x256"),
        (["--camera", "file:{d}/empty", "-l", "tcp/127.0.0.1:1"],
         "{d}/empty: folder holds no image (.png, .jpg, .jpeg, .jpe, .bmp, .dib, .tif, .tiff, "
         ".pgm, .ppm, .pbm, .pnm, .pam, .pxm, .webp, .jp2, .hdr, .pic, .pfm, .ras, .sr)"),
        # read before anything starts: up used to start all five, then end on the camera's
        # exit (code 1, no file named in a launch file)
        (["--camera", "file:{d}/junk.mp4", "-l", "tcp/127.0.0.1:1"],
         "{d}/junk.mp4: not a readable video"),
        (["--camera", "file:{d}/badfirst", "-l", "tcp/127.0.0.1:1"],
         "{d}/badfirst/a.png: not a readable image"),
        (["--camera", "device:x", "-l", "tcp/127.0.0.1:1"],
         "'device:x': the device index must be an integer 0..99, e.g. device:0"),
        (["-e", "nonsense"], "-e/--connect 'nonsense' is not a Zenoh endpoint: expected "
                             "<protocol>/<address>, e.g. tcp/127.0.0.1:7447"),
        (["-c", "{d}/bad.json5", "-l", "tcp/127.0.0.1:1"],
         "zenoh config file {d}/bad.json5: line 1, column 17: expected identifier or string"),
    ],
    "bench": [
        (["--bogus"], "unrecognized arguments: --bogus (see vistrack bench --help)"),
    ],
}


# run in a new interpreter: an offline command reading a damaged video, a service given a bad
# Zenoh config, a tool with a bad flag (what start-up or shutdown prints shows there only)
FRESH = {("track", "{d}/cut.avi"), ("track", "{d}/trunc.png"), ("track", "{d}/riff.avi"),
         ("camera", "-c"), ("echo", "camera/frame")}


@pytest.mark.parametrize(("sub", "argv", "message"),
                         [(sub, argv, message) for sub, cases in CASES.items()
                          for argv, message in cases],
                         ids=[f"{sub} {' '.join(argv)}" for sub, cases in CASES.items()
                              for argv, _ in cases])
def test_bad_input_is_one_line_and_exit_2(d, sub, argv, message):
    run = vistrack(sub, *(a.format(d=d) for a in argv), fresh=(sub, argv[0]) in FRESH)
    check(run, sub, message.format(d=d))


def test_a_damaged_recording_is_replayed_to_its_first_bad_record(d):
    """A record whose key cannot be published on is corrupt like any other bad record: the
    warning and the error name the file and the byte offset (it was a Zenoh error, exit 1)."""
    run = vistrack("replay", str(d / "badkey.rec"), "--wait", "0", NS)
    assert run.returncode == 2
    assert run.stderr.splitlines() == [
        f"vistrack replay: warning: {d}/badkey.rec is damaged: replayed the 0 valid samples "
        "before byte offset 79",
        f"vistrack replay: error: {d}/badkey.rec at byte offset 79: corrupt record: 'key' "
        "'vistrack/robot//frame' is not a key a sample can be published on (no empty chunk, "
        "wildcard, '#' or '?')"]


def test_a_video_cut_short_is_tracked_then_reported(d):
    """The frames a cut video still has are tracked and printed; then the one-line error."""
    run = vistrack("track", str(d / "cut.avi"), "--format", "csv")
    assert run.returncode == 2
    assert len(run.stdout.splitlines()) == 1 + 3  # the CSV header and three frames
    assert run.stderr.count("\n") == 1 and "ends after 3 of the 10 frames" in run.stderr


@pytest.mark.parametrize("sub", ["camera", "preprocessing", "status", "echo"])
def test_a_session_that_cannot_open_is_one_line_and_exit_1(sub):
    """An endpoint that is well formed but cannot be listened on (an address of no interface
    here) is a runtime failure: one line naming it, exit 1 (it was a traceback; the tools
    exited 2, as for bad flags), for services and tools alike."""
    if sub == "echo":
        sub_args: tuple[str, ...] = ("echo", "motion/estimate")
    else:
        sub_args = (sub,)
    run = vistrack(*sub_args, "-l", "tcp/192.0.2.1:7447", NS)  # TEST-NET-1: never local
    assert run.returncode == 1
    assert run.stderr.startswith(f"vistrack {sub}: error: cannot open zenoh session: ")
    assert "tcp/192.0.2.1:7447" in run.stderr and run.stderr.count("\n") == 1, run.stderr
