"""`python -m services.storage`: serve the storage service with settings from the environment."""

from services.common.runner import run_service
from services.storage.app import build_app
from services.storage.settings import StorageSettings

run_service("storage", build_app, StorageSettings)
