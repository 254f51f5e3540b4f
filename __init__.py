"""posefuse: multi-view 6D pose estimation of textureless, shiny, symmetric industrial parts.

The root of the repository is this package: ``posefuse.estimator`` (the algorithm),
``posefuse.sim``, ``posefuse.service``, ``posefuse.clients``, ``posefuse.bench`` and
``posefuse.cli`` are its folders, and ``catalogs/``, ``models/`` and ``recordings/`` travel with it
as package data (``posefuse.service.resources``)."""

__version__ = "0.1.0"
