"""Standard-library HTTP client for the job service and the Blender add-in. See issues 7, 8."""
