"""The robot daemon (a shell): the service loop, the local ingest socket, the crash-safe
journal and checkpoint, systemd notification.
"""
