"""The retargeting job service (FastAPI), built around retarget_core. See issue 7."""
