"""The version of evseg_torch (tagged ``vX.Y`` in git; see ``CHANGELOG.md``)."""

__version__ = "0.10.0"
