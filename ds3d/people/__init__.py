"""Finding people: where they are in an image, which of the poses found are people, and who is
who from frame to frame.

search.py       the whole-image search: the joint network over a pyramid, the PSM's root score
                as the detector (SearchParams, propose)
finder.py       PeopleFinder: which crops go through the 2D stage (find) and who is answered
                (answer); Candidate, Answer
same_person.py  when two poses are one person found twice
score.py        the person score, its evidence and its fit (PersonScore, read from the model)
tracking.py     people followed across a video's frames, their 3D joints smoothed (Tracker)
"""
