"""DanceGraph: music in, dance out."""

import os as _os

from dancegraph.paths import kernel_cache_dir as _kernel_cache_dir

__version__ = "0.1.0"

# numba reads NUMBA_CACHE_DIR when it is first imported: so every kernel (the project's and
# librosa's) caches in the one per-user folder, whichever module imports numba first, and the
# worker's children inherit the setting (dancegraph.jit).
_os.environ.setdefault("NUMBA_CACHE_DIR", str(_kernel_cache_dir()))
