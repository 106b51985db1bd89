"""`python -m services.fl`: serve the fl service with settings from the environment."""

from services.common.runner import run_service
from services.fl.app import build_app

run_service("fl", build_app)
