"""The retargeting job service (FastAPI) around retarget_core: a versioned REST API (``/v1``),
an embedded store (SQLite + files, :mod:`server.storage`), jobs run in their own processes
(:mod:`server.runner`, :mod:`server.job_process`), optionally spreading frames over Dask."""

import retarget_core  # noqa: E402,F401  before anything loads numpy: it pins the numerical kernels
