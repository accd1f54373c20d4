"""The ``spdslam`` command: ``info``, ``simulate``, ``run``, ``check``, ``evaluate``, ``import``,
``compare``, ``batch``, ``demo``, ``view``, ``warmup``. The top layer: it may import every other
package."""

from . import _check, _sequences, _simulate  # noqa: F401  (register the commands)
from ._app import CACHE_ENV as CACHE_ENV
from ._app import app as app
from ._app import cache_dir as cache_dir
from ._app import enable_compilation_cache as enable_compilation_cache
from ._app import fail as fail
from ._sequences import DEMO_MARKER as DEMO_MARKER

if __name__ == "__main__":  # pragma: no cover
    app()
