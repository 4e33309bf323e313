"""Persistence of scene records: the tables and the snapshots handed out (:mod:`service.db.rows`),
the store every API process and worker uses (:mod:`service.db.scenes`, with video builds in
:mod:`service.db.videos`), and the schema's migrations (:mod:`service.db.migrate`, revisions in
``migrations/``)."""
