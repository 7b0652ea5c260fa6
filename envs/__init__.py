"""dust-rl environments: MuJoCo tabletop suites controlled through mink."""

from .rendering import configure_headless_gl

configure_headless_gl()

from .env import DustEnv  # noqa: E402
from .tasks import list_tasks, make_task  # noqa: E402

__all__ = ["DustEnv", "list_tasks", "make_task"]
