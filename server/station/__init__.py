"""The station process: the station (core, the façade over its rooms: measuring, triggers,
recorder, links, queries; rehearsal), its control channel (messages, control, client) and its
main (process)."""
