"""A misbehaving stand-in for `python3 -m kestimator.worker`, for the Klipper module's tests:
`fake_worker.py MODE` (the module starts it through a shell script named as its python).

  huge          answers the first request with a line of 20 MiB
  garbage       answers the first request with a line that is not JSON
  mute          never reads its input (the pipe fills up)
  stderr-exit   says why on stderr and exits 1 at once
  die           reads the first request, says so on stderr and exits 3
"""
import sys
import time


def main() -> int:
    mode = sys.argv[1]
    if mode == "stderr-exit":
        sys.stderr.write("Traceback (most recent call last):\n  File \"x\", line 1\n"
                         "ModuleNotFoundError: No module named 'kestimator'\n")
        return 1
    if mode == "mute":
        time.sleep(60)
        return 0
    sys.stdin.buffer.readline()
    if mode == "die":
        sys.stderr.write("MemoryError: killed while estimating\n")
        sys.stderr.flush()
        return 3
    out = sys.stdout.buffer
    if mode == "huge":
        chunk = b"x" * (1 << 20)
        for _ in range(20):
            out.write(chunk)
        out.write(b"\n")
    elif mode == "garbage":
        out.write(b"this is not JSON\n")
    out.flush()
    time.sleep(60)
    return 0


if __name__ == "__main__":
    sys.exit(main())
