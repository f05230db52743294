// Sorting dropped files into the upload form's fields (service/web/js/upload_files.js).
import assert from "node:assert/strict";
import { test } from "node:test";

import { addToChoice, choiceSummary, emptyChoice, fileRole } from "../../../service/web/js/upload_files.js";

test("each file goes to the field the service takes it in", () => {
  assert.equal(fileRole("0001.PNG"), "images");
  assert.equal(fileRole("a.jpeg"), "images");
  assert.equal(fileRole("b.jpg"), "images");
  assert.equal(fileRole("matching3.txt"), "matches");
  assert.equal(fileRole("calibration.txt"), "calibration");
  assert.equal(fileRole("photos.zip"), "zip");
  assert.equal(fileRole("notes.pdf"), null);
  assert.equal(fileRole("matching.txt"), "calibration"); // no number: not a match file
});

test("a choice collects photos and match files, keeps the last calibration and zip, reports the rest", () => {
  const chosen = emptyChoice();
  const leftOut = addToChoice(chosen, [{ name: "1.png" }, { name: "matching1.txt" }, { name: "K1.txt" },
    { name: "x.gif" }, { name: "2.jpg" }, { name: "K2.txt" }]);
  assert.deepEqual(leftOut, ["x.gif"]);
  assert.deepEqual(chosen.images.map((f) => f.name), ["1.png", "2.jpg"]);
  assert.equal(chosen.calibration.name, "K2.txt");
  assert.equal(choiceSummary(chosen), "2 photo(s), 1 match file(s), calibration: K2.txt");
  addToChoice(chosen, [{ name: "all.zip" }]);
  assert.equal(choiceSummary(chosen), "2 photo(s) and all.zip, 1 match file(s), calibration: K2.txt");
  assert.equal(choiceSummary(emptyChoice()), "0 photo(s), 0 match file(s), calibration: none");
});
