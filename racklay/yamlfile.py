"""Read a YAML file that must hold a mapping (training configs, WareSynth recipes): one reader,
one set of one-line errors naming the file."""
from __future__ import annotations

import os
from pathlib import Path


def read_yaml_mapping(path: str | os.PathLike, what: str = "key: value", error: type = ValueError) -> dict:
    """The mapping in YAML file `path` ({} for an empty file). Raises FileNotFoundError for a
    missing file and `error` (a ValueError subclass) for invalid YAML or a non-mapping, with a
    message that names the file; `what` says what the mapping should hold."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise error(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file") from None
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping of {what}")
    return data
