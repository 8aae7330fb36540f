"""Safe YAML reading: no object construction, duplicate keys refused, errors name the file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from pipeline.errors import ConfigError


class _StrictSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate mapping keys (PyYAML silently keeps the last)."""


def _construct_mapping(loader: _StrictSafeLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    loader.flatten_mapping(node)
    mapping: dict[Any, Any] = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in mapping:
            mark = key_node.start_mark
            raise ConfigError(f"{mark.name}:{mark.line + 1}: duplicate key '{key}'; keep only one")
        mapping[key] = loader.construct_object(value_node, deep=deep)
    return mapping


_StrictSafeLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_yaml_text(text: str, name: str) -> Any:
    """Parse YAML ``text`` safely; ``name`` (a file name) appears in errors."""
    try:
        loader = _StrictSafeLoader(text)
        loader.name = name
        try:
            return loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as err:
        raise ConfigError(f"{name}: not valid YAML: {err}") from None


def read_yaml_mapping(path: Path, display: str | None = None, *, required: bool = True) -> dict:
    """Read a YAML file whose top level must be a mapping (an empty file is ``{}``)."""
    name = display or str(path)
    if not path.is_file():
        if required:
            raise ConfigError(f"{name}: file not found")
        return {}
    data = load_yaml_text(path.read_text(encoding="utf-8"), name)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{name}: the top level must be a mapping (key: value), got {type(data).__name__}")
    return data
