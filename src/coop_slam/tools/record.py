"""Record RViz to an MP4 (plus a final PNG), headless if need be: the logic behind
``scripts/record_rviz``.

Starts Xvfb (software GL) when there is no DISPLAY or ``--headless`` is given, RViz full screen with
``rviz/coop_slam.rviz`` and ``ffmpeg -f x11grab``; stops after ``--duration`` seconds, when
``--until-topic`` (std_msgs/Bool) carries true, or on SIGINT/SIGTERM; then saves the screen as a PNG
and ends every child process (each runs in its own process group), also on errors and a second
Ctrl-C. Writes ``OUT/rviz.mp4`` and ``OUT/map.png``. Needs a reachable ROS master (ROS_MASTER_URI).
"""

from __future__ import annotations

import argparse
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import CoopSlamError

CONFIG_NAME = "coop_slam.rviz"
DEFAULT_SIZE = (1280, 720)  # screen / video size (scripts/demo frames its view for this aspect)
# Topics every rviz subscribes to on its own; a subscription to anything else means the displays
# of the config are loaded.
_RVIZ_OWN_TOPICS = {"/tf", "/tf_static", "/clock", "/rosout"}


class RecordError(CoopSlamError):
    """Something the recording needs is missing or failed (message says what)."""


class Interrupted(Exception):
    """SIGINT/SIGTERM arrived before the recording started."""


def say(msg: str) -> None:
    print(f"[record] {msg}", flush=True)


# --- arguments ------------------------------------------------------------------------------------
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"size '{text}' is not WIDTHxHEIGHT, e.g. 1280x720"
        ) from None
    if not (64 <= w <= 8192 and 64 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"size {w}x{h} out of range (64..8192 per side)")
    return w, h


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} is not > 0")
    return value


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="scripts/record_rviz", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--out", default="record", help="output folder for rviz.mp4 and map.png [record]"
    )
    p.add_argument("--config", help=f"RViz config [the package's rviz/{CONFIG_NAME}]")
    p.add_argument(
        "--duration", type=_positive, metavar="S", help="stop after S seconds of recording"
    )
    p.add_argument(
        "--until-topic",
        metavar="TOPIC",
        help="stop when this std_msgs/Bool topic carries true (e.g. /player/done)",
    )
    p.add_argument(
        "--size",
        type=_size,
        default=DEFAULT_SIZE,
        help=f"screen / video size [{DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]}]",
    )
    p.add_argument("--framerate", type=_positive, default=10.0, help="video frame rate [10]")
    p.add_argument("--headless", action="store_true", help="use Xvfb even when DISPLAY is set")
    p.add_argument(
        "--warmup",
        type=float,
        default=2.0,
        metavar="S",
        help="wait S seconds after RViz has loaded its displays before recording [2]",
    )
    p.add_argument(
        "--master-timeout",
        type=_positive,
        default=10.0,
        metavar="S",
        help="give up when no ROS master answers within S seconds [10]",
    )
    p.add_argument(
        "--rviz-timeout",
        type=_positive,
        default=60.0,
        metavar="S",
        help="give up when RViz has not loaded its displays within S seconds [60]",
    )
    return p.parse_args(argv)


# --- helpers --------------------------------------------------------------------------------------
def find_config(explicit: str | None = None) -> Path:
    """``explicit``, else rviz/coop_slam.rviz next to the script, the source tree or
    ``rospack find``."""
    if explicit:
        path = Path(explicit).expanduser()
        if not path.is_file():
            raise RecordError(f"RViz config {path} not found")
        return path.resolve()
    candidates = []
    if sys.argv and sys.argv[0]:
        candidates.append(Path(sys.argv[0]).resolve().parent.parent / "rviz" / CONFIG_NAME)
    candidates.append(Path(__file__).resolve().parents[3] / "rviz" / CONFIG_NAME)
    try:
        pkg = subprocess.run(
            ["rospack", "find", "coop_slam"], capture_output=True, text=True, timeout=20
        ).stdout.strip()
        if pkg:
            candidates.append(Path(pkg) / "rviz" / CONFIG_NAME)
    except (OSError, subprocess.TimeoutExpired):
        pass
    for path in candidates:
        if path.is_file():
            return path
    raise RecordError(
        f"rviz/{CONFIG_NAME} not found (looked at {', '.join(map(str, candidates))}); "
        "pass --config"
    )


def master_uri() -> str:
    return os.environ.get("ROS_MASTER_URI", "http://localhost:11311")


def _master():
    import rosgraph

    return rosgraph.Master(f"/record_rviz_{os.getpid()}", master_uri=master_uri())


def _with_timeout(seconds: float, fn):
    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(seconds)
    try:
        return fn()
    finally:
        socket.setdefaulttimeout(old)


def encoder_args() -> tuple[str, list[str]]:
    """H.264 (libx264) when Debian's ffmpeg has it, else MPEG-4 part 2; yuv420p either way."""
    try:
        encoders = subprocess.run(
            ["ffmpeg", "-hide_banner", "-encoders"], capture_output=True, text=True, timeout=30
        ).stdout
    except (OSError, subprocess.TimeoutExpired):
        encoders = ""
    if any(line.split()[1:2] == ["libx264"] for line in encoders.splitlines()):
        return "libx264", [
            "-c:v",
            "libx264",
            "-preset",
            "veryfast",
            "-crf",
            "23",
            "-pix_fmt",
            "yuv420p",
        ]
    return "mpeg4", ["-c:v", "mpeg4", "-q:v", "4", "-pix_fmt", "yuv420p"]


def patched_config(src: Path, dst: Path, size: tuple[int, int]) -> Path:
    """Copy of the config whose window covers the screen (0, 0, width, height)."""
    import yaml

    with open(src, encoding="utf-8") as fh:
        cfg = yaml.safe_load(fh)
    if not isinstance(cfg, dict):
        raise RecordError(f"{src} is not an RViz config (YAML mapping)")
    geom = cfg.setdefault("Window Geometry", {})
    geom.update({"X": 0, "Y": 0, "Width": size[0], "Height": size[1]})
    cfg.setdefault("Preferences", {})["PromptSaveOnExit"] = False
    with open(dst, "w", encoding="utf-8") as fh:
        yaml.safe_dump(cfg, fh, sort_keys=False)
    return dst


def _tail(path: Path, n: int = 2000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    log: Path | None = None
    stop_signal: int = signal.SIGTERM

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, grace: float = 5.0) -> None:
        """Signal the child's process group, wait ``grace`` s, then SIGKILL the group."""
        for sig, wait in ((self.stop_signal, grace), (signal.SIGKILL, 5.0)):
            try:
                os.killpg(self.proc.pid, sig)  # each child leads its own process group
            except (ProcessLookupError, PermissionError):
                pass
            try:
                self.proc.wait(timeout=wait)
                break
            except subprocess.TimeoutExpired:
                continue
        # the leader may be gone while others of its group live on
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


# --- the recorder ---------------------------------------------------------------------------------
class Recorder:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.children: list[Child] = []
        self.stop_reason: str | None = None
        self.signals = 0
        self.tmp = Path(tempfile.mkdtemp(prefix="record_rviz_"))
        self.display = os.environ.get("DISPLAY", "")
        self.env = dict(os.environ)
        self.done_flag = False

    # signals: the first asks for a graceful stop, the second aborts (cleanup still runs)
    def on_signal(self, signum, _frame) -> None:
        self.signals += 1
        name = signal.Signals(signum).name
        if self.signals > 1:
            raise KeyboardInterrupt(name)
        self.stop_reason = f"{name} received"

    def check_interrupt(self) -> None:
        if self.stop_reason is not None:
            raise Interrupted(self.stop_reason)

    def spawn(self, name: str, cmd: list[str], stop_signal=signal.SIGTERM, log=True, **kw) -> Child:
        log_path = self.tmp / f"{name}.log" if log else None
        out = open(log_path, "wb") if log_path else subprocess.DEVNULL
        try:
            proc = subprocess.Popen(
                cmd,
                stdout=out,
                stderr=subprocess.STDOUT,
                env=self.env,
                start_new_session=True,
                **kw,
            )
        except OSError as exc:
            raise RecordError(f"cannot start {cmd[0]}: {exc}") from None
        finally:
            if log_path:
                out.close()
        child = Child(name, proc, log_path, stop_signal)
        self.children.append(child)
        return child

    def cleanup(self) -> None:
        for child in reversed(self.children):  # ffmpeg, rviz, then Xvfb
            if child.alive():
                child.stop()
            else:
                try:
                    os.killpg(child.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
        self.children.clear()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def fail(self, msg: str, child: Child | None = None) -> RecordError:
        if child is not None and child.log is not None:
            tail = _tail(child.log)
            if tail.strip():
                msg += f"\n--- last lines of {child.name}'s output:\n{tail.rstrip()}"
        return RecordError(msg)

    # steps
    def wait_for_master(self) -> None:
        uri = master_uri()
        deadline = time.monotonic() + self.args.master_timeout
        while True:
            self.check_interrupt()
            try:
                _with_timeout(2.0, lambda: _master().getPid())
                say(f"ROS master at {uri}")
                return
            except Exception:  # noqa: BLE001 - connection refused, timeouts, DNS: all "not there"
                if time.monotonic() > deadline:
                    raise RecordError(
                        f"no ROS master reachable at {uri} within {self.args.master_timeout:g} s: "
                        "rviz needs one; start roscore (or set ROS_MASTER_URI)"
                    ) from None
                time.sleep(0.3)

    def start_xvfb(self) -> None:
        if shutil.which("Xvfb") is None:
            raise RecordError("Xvfb not found: install Debian's 'xvfb' (see debian-packages.txt)")
        w, h = self.args.size
        r, wfd = os.pipe()
        try:
            # -displayfd: Xvfb takes the first free display number and writes it once it accepts
            # clients
            xvfb = self.spawn(
                "Xvfb",
                ["Xvfb", "-displayfd", str(wfd), "-screen", "0", f"{w}x{h}x24", "-nolisten", "tcp"],
                pass_fds=(wfd,),
            )
            os.close(wfd)
            wfd = -1
            text = b""
            deadline = time.monotonic() + 20.0
            while not text.endswith(b"\n"):
                self.check_interrupt()
                if time.monotonic() > deadline or not xvfb.alive():
                    raise self.fail("Xvfb did not start", xvfb)
                ready, _, _ = select.select([r], [], [], 0.2)
                if ready:
                    chunk = os.read(r, 64)
                    if not chunk:
                        raise self.fail("Xvfb did not start", xvfb)
                    text += chunk
        finally:
            os.close(r)
            if wfd >= 0:
                os.close(wfd)
        self.display = f":{int(text.strip())}"
        self.env["DISPLAY"] = self.display
        self.env["LIBGL_ALWAYS_SOFTWARE"] = "1"  # no GPU behind Xvfb: Mesa's software rasterizer
        say(f"Xvfb on {self.display} ({w}x{h}, software GL, pid {xvfb.pid})")

    def start_rviz(self, config: Path) -> Child:
        if shutil.which("rviz") is None:
            raise RecordError("rviz not found: install Debian's 'rviz' (see debian-packages.txt)")
        node = f"record_rviz_viewer_{os.getpid()}"
        cfg = patched_config(config, self.tmp / CONFIG_NAME, self.args.size)
        # SIGTERM (not SIGINT) at the end: rviz then skips saving the temporary config as the user's
        # "last config" in ~/.rviz/persistent_settings
        rviz = self.spawn(
            "rviz",
            ["rviz", "--fullscreen", "-d", str(cfg), f"__name:={node}"],
            stdin=subprocess.DEVNULL,
        )
        say(f"rviz -d {config} on {self.display} (pid {rviz.pid})")
        t0 = time.monotonic()
        deadline = t0 + self.args.rviz_timeout
        me = f"/{node}"
        registered = False
        while True:
            self.check_interrupt()
            if not rviz.alive():
                raise self.fail(f"rviz exited with status {rviz.proc.returncode}", rviz)
            try:
                _, subs, _ = _with_timeout(2.0, lambda: _master().getSystemState())
                topics = {t for t, nodes in subs if me in nodes}
                registered = registered or bool(topics)
                if topics - _RVIZ_OWN_TOPICS:
                    break
            except Exception:  # noqa: BLE001 - a busy master: ask again
                pass
            if time.monotonic() > deadline:
                if registered:
                    say(
                        f"rviz subscribed to no display topic within {self.args.rviz_timeout:g} s; "
                        "recording anyway"
                    )
                    break
                raise self.fail(f"rviz did not come up within {self.args.rviz_timeout:g} s", rviz)
            time.sleep(0.25)
        say(f"rviz ready after {time.monotonic() - t0:.1f} s")
        end = time.monotonic() + max(0.0, self.args.warmup)
        while time.monotonic() < end:  # first frames under software GL
            self.check_interrupt()
            time.sleep(0.1)
        return rviz

    def _grab_input(self) -> list[str]:
        w, h = self.args.size
        return [
            "-f",
            "x11grab",
            "-draw_mouse",
            "0",
            "-video_size",
            f"{w}x{h}",
            "-i",
            f"{self.display}+0,0",
        ]

    def start_ffmpeg(self, mp4: Path) -> Child:
        name, codec = encoder_args()
        fps = f"{self.args.framerate:g}"
        cmd = (
            ["ffmpeg", "-hide_banner", "-loglevel", "warning", "-y", "-framerate", fps]
            + self._grab_input()
            + ["-vf", "scale=trunc(iw/2)*2:trunc(ih/2)*2"]
            + codec
            + ["-r", fps, "-movflags", "+faststart", str(mp4)]
        )
        ffmpeg = self.spawn("ffmpeg", cmd, stop_signal=signal.SIGINT, stdin=subprocess.PIPE)
        say(f"recording {self.display} to {mp4} ({name}, {fps} fps, pid {ffmpeg.pid})")
        return ffmpeg

    def stop_ffmpeg(self, ffmpeg: Child) -> None:
        """'q' makes ffmpeg finish the file; SIGINT, then the usual group stop, if it does not."""
        try:
            ffmpeg.proc.stdin.write(b"q")
            ffmpeg.proc.stdin.close()
        except (BrokenPipeError, OSError, ValueError):
            pass
        try:
            ffmpeg.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            ffmpeg.stop(grace=10.0)
        self.children.remove(ffmpeg)

    def screenshot(self, png: Path) -> None:
        cmd = (
            ["ffmpeg", "-hide_banner", "-loglevel", "error", "-y"]
            + self._grab_input()
            + ["-frames:v", "1", str(png)]
        )
        try:
            proc = subprocess.run(
                cmd,
                capture_output=True,
                text=True,
                timeout=30,
                env=self.env,
                start_new_session=True,
            )
        except subprocess.TimeoutExpired:
            raise RecordError("ffmpeg took over 30 s to grab the final PNG") from None
        if proc.returncode != 0 or not png.is_file():
            raise RecordError(f"final PNG failed: {proc.stderr.strip()[-500:]}")
        say(f"wrote {png}")

    def subscribe_done(self):
        import rospy
        from std_msgs.msg import Bool

        rospy.init_node(f"record_rviz_{os.getpid()}", disable_signals=True, disable_rosout=True)

        def done(msg):
            if msg.data:
                self.done_flag = True

        return rospy.Subscriber(self.args.until_topic, Bool, done, queue_size=10)

    def run(self) -> int:
        args = self.args
        if shutil.which("ffmpeg") is None:
            raise RecordError(
                "ffmpeg not found: install Debian's 'ffmpeg' (see debian-packages.txt)"
            )
        config = find_config(args.config)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        mp4, png = out / "rviz.mp4", out / "map.png"
        self.wait_for_master()
        sub = self.subscribe_done() if args.until_topic else None
        if args.headless or not self.display:
            self.start_xvfb()
        else:
            say(
                f"using DISPLAY={self.display} (rviz goes full screen; the top-left "
                f"{args.size[0]}x{args.size[1]} is recorded)"
            )
        rviz = self.start_rviz(config)
        ffmpeg = self.start_ffmpeg(mp4)
        t0 = time.monotonic()
        if args.until_topic:
            say(f"waiting for true on {args.until_topic}")
        if not args.duration and not args.until_topic:
            say("recording until Ctrl-C")
        failure = None
        while True:
            if self.stop_reason:
                say(f"stop: {self.stop_reason}")
                break
            if args.duration and time.monotonic() - t0 >= args.duration:
                say(f"stop: {args.duration:g} s recorded")
                break
            if self.done_flag:
                say(f"stop: true on {args.until_topic}")
                break
            if not ffmpeg.alive():
                failure = self.fail(f"ffmpeg exited with status {ffmpeg.proc.returncode}", ffmpeg)
                break
            if not rviz.alive():
                failure = self.fail(f"rviz exited with status {rviz.proc.returncode}", rviz)
                break
            time.sleep(0.05)
        seconds = time.monotonic() - t0
        if sub is not None:
            sub.unregister()
        if rviz.alive():
            try:
                self.screenshot(png)
            except RecordError as exc:
                failure = failure or exc
        self.stop_ffmpeg(ffmpeg)
        if not mp4.is_file() or mp4.stat().st_size == 0:
            raise failure or self.fail(f"ffmpeg wrote no video to {mp4}", ffmpeg)
        say(f"wrote {mp4} ({mp4.stat().st_size / 1024:.0f} kB, {seconds:.1f} s)")
        if failure:
            raise failure
        return 0


def main(argv=None) -> int:
    args = parse_args(argv)
    rec = Recorder(args)
    old = {s: signal.signal(s, rec.on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        status = rec.run()
        say("done")
        return status
    except RecordError as exc:
        say(f"ERROR: {exc}")
        return 1
    except (Interrupted, KeyboardInterrupt) as exc:
        say(
            f"interrupted ({exc}) - nothing recorded"
            if isinstance(exc, Interrupted)
            else f"aborted ({exc})"
        )
        return 130
    finally:
        for s in old:  # a further Ctrl-C must not cut the cleanup short
            signal.signal(s, signal.SIG_IGN)
        rec.cleanup()
        for s, handler in old.items():
            signal.signal(s, handler)
        if args.until_topic:
            try:
                import rospy

                rospy.signal_shutdown("record_rviz done")
            except Exception:  # noqa: BLE001 - rospy never started
                pass


if __name__ == "__main__":
    sys.exit(main())
