"""Recording U2SA traffic to MCAP and reading it back (issue: record and replay).

``schemas`` turns LCM types into MCAP schemas, ``mcap_log`` writes logs (chunked,
indexed, flushed every second, rotated), ``log_reader`` reads logs -- including
truncated ones -- and recovers them, ``foxglove`` exports a JSON copy Foxglove can show.
"""
