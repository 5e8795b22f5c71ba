"""What a map becomes: PLY/mcap/Nav2 exports, renders, reports, evaluation and scores."""
