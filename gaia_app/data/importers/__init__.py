"""Importers that turn external recordings into clip folders (`gaia_app.data.clip_folder`).

- `dashcam.import_dashcam`: a plain video file, any frame rate, no labels.
- `pandaset.import_pandaset`: a PandaSet sequence, six cameras with rig, ego motion and 3D agents.

Each module is also a command line tool (`python -m gaia_app.data.importers.dashcam --help`).
The modules are not imported here so that `python -m` runs them without a double import.
"""
