"""`python -m services.cas`: serve the cas service with settings from the environment."""

from services.cas.app import build_app
from services.cas.settings import CasSettings
from services.common.runner import run_service

run_service("cas", build_app, CasSettings)
