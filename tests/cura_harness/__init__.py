"""Test equipment for the Cura plugin's tests, not part of the plugin or its package.

``curaengine.py`` is imported by the tests; ``uranium_host.py`` (Debian's ``/usr/bin/python3``
with Cura's modules) and ``gui_check.py`` (beside a real Cura under Xvfb) are run as scripts
by path, each importing only its own folder's modules.
"""
