"""tools/install.py: pip's configuration passed on to uv."""

import importlib.util
from pathlib import Path

spec = importlib.util.spec_from_file_location("install", Path(__file__).resolve().parents[2] / "tools" / "install.py")
install = importlib.util.module_from_spec(spec)
spec.loader.exec_module(install)

LISTING = """global.cert='/etc/ssl/certs/ca-certificates.crt'
global.constraint='/etc/xdg/pip/constraints.txt'
global.extra-index-url='file:///opt/pypi/simple file:///opt/pypi-more/simple'
global.find-links='/opt/old'
:env:.find-links='/opt/wheels'
:env:.default-timeout='180'
"""


def test_indexes_wheel_folders_and_constraints_reach_uv_as_pip_uses_them():
    settings = install.parse_pip_config(LISTING)
    assert settings == {"constraint": ["/etc/xdg/pip/constraints.txt"], "find-links": ["/opt/wheels"],
                        "extra-index-url": ["file:///opt/pypi/simple", "file:///opt/pypi-more/simple"]}
    assert install.uv_options(settings) == [
        "--find-links", "/opt/wheels", "--extra-index-url", "file:///opt/pypi/simple", "--extra-index-url",
        "file:///opt/pypi-more/simple", "--constraint", "/etc/xdg/pip/constraints.txt",
        "--index-strategy", "unsafe-best-match"]


def test_without_pip_configuration_uv_keeps_its_defaults():
    assert install.uv_options(install.parse_pip_config("")) == []
    assert install.uv_options(install.parse_pip_config("global.index-url='https://mirror.example/simple'\n")) == [
        "--index-url", "https://mirror.example/simple"]
