"""What the Python benches share: a multipart/form-data body and a POST
that returns the status, the seconds it took and the error message."""
import io
import json
import time
import urllib.error
import urllib.request
import uuid


def multipart(parts):
    """The body and Content-Type of `parts`: (name, content type, bytes)."""
    boundary = uuid.uuid4().hex
    out = io.BytesIO()
    for name, ctype, data in parts:
        out.write(f"--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{name}\"\r\n"
                  f"Content-Type: {ctype}\r\n\r\n".encode())
        out.write(data)
        out.write(b"\r\n")
    out.write(f"--{boundary}--\r\n".encode())
    return out.getvalue(), f"multipart/form-data; boundary={boundary}"


def request(url, body=None, ctype=None, timeout=120):
    """(status or "error", seconds, the error message of a JSON error body)."""
    req = urllib.request.Request(url, data=body, headers={"Content-Type": ctype} if ctype else {})
    t = time.monotonic()
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            r.read()
            status, msg = r.status, ""
    except urllib.error.HTTPError as e:
        status, raw = e.code, e.read() or b"{}"
        try:
            msg = json.loads(raw).get("error", "")
        except ValueError:
            msg = raw.decode(errors="replace")
    except OSError as e:
        status, msg = "error", str(e)
    return status, time.monotonic() - t, msg


def rss_kb(pid):
    """A process's resident memory in KiB, from /proc."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1])
    return 0


def ready(base):
    """Whether the server at `base` answers its readiness probe 200."""
    try:
        with urllib.request.urlopen(base + "/health/ready", timeout=2) as r:
            return r.status == 200
    except (urllib.error.HTTPError, OSError):
        return False
