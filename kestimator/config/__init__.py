"""Where a printer's limits come from.

``printer_cfg`` reads a Klipper printer.cfg, ``moonraker`` a running printer's settings (with
an offline cache), ``profile`` the user's TOML profile, ``fields`` checks values a person gives;
``resolve`` combines them with the slicer's settings (``kestimator.slicers``) into one
``Limits`` with the provenance of every value. docs/LIMITS.md describes the order.
"""
