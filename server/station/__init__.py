"""The station process: cameras, links, the trigger thread, the pipeline and the record of every
answer (core), its control channel (control, client) and its main (process)."""
