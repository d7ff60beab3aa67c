"""io.digest.file_digest: the file's sha256, recomputed when the file changes under the same path (the cache is
keyed by mtime and size), and a missing file is an InputError that names it."""
import hashlib
import os

import pytest

from hgca_core.errors import InputError
from hgca_core.io.digest import file_digest


def test_the_digest_follows_the_file_not_the_path(tmp_path):
    f = tmp_path / "w.pt"
    f.write_bytes(b"a" * 3_000_000)                      # more than one read block
    assert file_digest(f) == hashlib.sha256(b"a" * 3_000_000).hexdigest()
    f.write_bytes(b"b" * 3_000_000)                      # same size: the mtime tells the cache apart
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert file_digest(f) == hashlib.sha256(b"b" * 3_000_000).hexdigest()
    with pytest.raises(InputError, match="file not found") as e:
        file_digest(tmp_path / "gone.pt")
    assert "gone.pt" in str(e.value)
