"""Dataparsers for the layouts FrugalNeRF is evaluated on, all with the same few-shot view selection."""
