"""RackLay toolkit: per-shelf top- and front-view layouts of warehouse racks from one photo.

Modules: `layout` (the one layout convention), `data` (RackLay-format datasets), `metrics`,
`viz` (figures), `torchdata` (torch Dataset). See docs/architecture.md.
"""
__version__ = "0.1.0"
