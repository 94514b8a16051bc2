"""Every test's caches in a folder of its own session, never the user's (~/.cache/dinerf)."""

import os
import tempfile

os.environ.setdefault("DINERF_CACHE", tempfile.mkdtemp(prefix="dinerf-test-cache-"))
