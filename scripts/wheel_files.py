"""What the fetch_* scripts share: a download with retries, the check of a wheel's files against
its RECORD, and an install made in a temporary directory and renamed into place (so concurrent runs
and interrupted ones never leave a half-made install behind). Standard library only.
"""
import base64
import hashlib
import os
import shutil
import sys
import tempfile
import time
import urllib.request


def http_get(url, who, timeout=120):
    """The body of `url`, retried 5 times with backoff; `who` prefixes the retry messages."""
    for attempt in range(5):
        try:
            with urllib.request.urlopen(url, timeout=timeout) as r:
                return r.read()
        except OSError as e:
            if attempt == 4:
                raise
            print(f"{who}: retrying {url} after: {e}", file=sys.stderr)
            time.sleep(2 ** attempt)


def download_checked(url, sha256, path, who, timeout=300):
    """Downloads `url` into `path` after checking its sha256 (a mismatch ends the script); returns
    its size in bytes."""
    data = http_get(url, who, timeout=timeout)
    if hashlib.sha256(data).hexdigest() != sha256:
        sys.exit(f"{who}: sha256 mismatch for {url}")
    write_file(path, data)
    return len(data)


def record_hashes(zf):
    """The urlsafe-base64 sha256 of every file a wheel's .dist-info/RECORD lists."""
    rec = [n for n in zf.namelist() if n.endswith(".dist-info/RECORD")][0]
    hashes = {}
    for line in zf.read(rec).decode().splitlines():
        parts = line.rsplit(",", 2)
        if len(parts) == 3 and parts[1].startswith("sha256="):
            hashes[parts[0]] = parts[1][len("sha256="):]
    return hashes


def read_checked(zf, hashes, member, who, source):
    """A wheel member's bytes, after checking them against the RECORD (`hashes`); a mismatch ends
    the script with a message naming the member and `source` (the wheel's URL or name)."""
    blob = zf.read(member)
    digest = base64.urlsafe_b64encode(hashlib.sha256(blob).digest()).rstrip(b"=").decode()
    if hashes.get(member) != digest:
        sys.exit(f"{who}: sha256 mismatch for {member} in {source}")
    return blob


def write_file(path, blob):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as out:
        out.write(blob)


def install_atomically(root, name, version, populate):
    """Installs `root/name` at `version` unless it is there: `populate(tmp)` fills a temporary
    directory beside it, which gets a `build-version` stamp and is renamed into place. Returns
    populate's result, or None when the install was already there."""
    dest = os.path.join(root, name)
    stamp = os.path.join(dest, "build-version")
    if os.path.exists(stamp) and open(stamp).read().strip() == version:
        return None  # already installed
    os.makedirs(root, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=f".{name}-", dir=root)
    try:
        result = populate(tmp)
        with open(os.path.join(tmp, "build-version"), "w") as out:
            out.write(version + "\n")
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the install is an ordinary folder
        if os.path.exists(dest):
            shutil.rmtree(dest)
        try:
            os.rename(tmp, dest)
        except OSError:
            if not os.path.exists(stamp):  # lost a race to a concurrent run that did not finish
                raise
        return result
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
