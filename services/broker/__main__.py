"""`python -m services.broker`: serve the broker service with settings from the environment."""

from services.broker.app import build_app
from services.common.runner import run_service

run_service("broker", build_app)
