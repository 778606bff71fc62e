"""The file formats shared by the API and the pipeline: one reader (and writer) per format.

Standard library only, so both sides import it without importing each other (the API never
imports the workers; the pipeline imports nothing else from app/). Every reader raises
:class:`~app.formats.errors.FormatError` naming the document and field at fault; the API
answers it as 422 (413 for :class:`~app.formats.errors.FormatTooLarge`), a pipeline stage
raises its InputError.

- :mod:`app.formats.cameras`: cameras.json (intrinsics, env_from_cam poses), its JSON Schema.
- :mod:`app.formats.yolo`: YOLO label files.
- :mod:`app.formats.reference`: an environment's marker reference (ArUco sheet).
"""

from app.formats.errors import FormatError, FormatTooLarge

__all__ = ["FormatError", "FormatTooLarge"]
