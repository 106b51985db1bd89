"""`python -m services.storage`: serve the storage service with settings from the environment."""

from services.common.runner import BUSY_THREADS_SWITCH_INTERVAL_S, run_service
from services.storage.app import build_app
from services.storage.settings import StorageSettings

# Record queries scan up to a million documents on worker threads.
run_service("storage", build_app, StorageSettings, switch_interval_s=BUSY_THREADS_SWITCH_INTERVAL_S)
