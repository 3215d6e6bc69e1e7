"""The application layer: what each ``trimag`` command does with files, one module per job.

Every entry point takes one typed request (:mod:`trimag.requests`), reads through :mod:`trimag.io`, works through
the library, writes its outputs atomically and returns a result the CLI prints. :mod:`trimag.workflow` re-exports
the entry points under their stable names. See docs/architecture.md (the app layer).
"""
