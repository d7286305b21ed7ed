// quantacolor user study (written by `quantacolor report --study`; supplement §4, Fig. 11):
// for each scene, its renderings side by side in the (seeded) random order of study-data.js,
// two questions each; vote by clicking an image or pressing its number (1-9). The votes are
// downloaded as JSON (format "quantacolor-study-votes", read by `quantacolor report --tally`).
"use strict";
(function () {
  const data = window.QC_STUDY;
  const $ = (id) => document.getElementById(id);
  const votes = [];
  let trial = 0;
  let question = 0;
  let shownAt = 0;

  function finished() {
    return trial >= data.trials.length;
  }

  function show() {
    const box = $("choices");
    box.textContent = "";
    $("count").textContent = String(votes.length);
    if (finished()) {
      $("question").textContent = "";
      $("progress").textContent = "";
      $("done").hidden = false;
      return;
    }
    const t = data.trials[trial];
    const n = t.images.length;
    $("progress").textContent =
      "Scene " + (trial + 1) + " of " + data.trials.length + ", question " + (question + 1) + " of " + data.questions.length + ".";
    $("question").textContent = data.questions[question].text;
    t.images.forEach((src, i) => {
      const fig = document.createElement("figure");
      fig.className = "choice";
      fig.id = "choice-" + (i + 1);
      const img = document.createElement("img");
      img.src = src;
      img.alt = "image " + (i + 1);
      // Side by side across the window, scaled up or down alike (pixelated when enlarged).
      img.style.width = "calc((100vw - " + (40 + 18 * n) + "px) / " + n + ")";
      const cap = document.createElement("figcaption");
      cap.textContent = String(i + 1);
      fig.append(img, cap);
      fig.addEventListener("click", () => vote(i));
      box.append(fig);
    });
    shownAt = performance.now();
  }

  function vote(i) {
    if (finished()) {
      return;
    }
    const t = data.trials[trial];
    if (i < 0 || i >= t.labels.length) {
      return;
    }
    votes.push({
      scene: t.scene,
      question: data.questions[question].id,
      choice: t.labels[i],
      position: i + 1,
      order: t.labels.slice(),
      ms: Math.round(performance.now() - shownAt),
    });
    question += 1;
    if (question >= data.questions.length) {
      question = 0;
      trial += 1;
    }
    show();
  }

  function votesJson() {
    return JSON.stringify(
      {
        format: "quantacolor-study-votes",
        version: 1,
        title: data.title,
        seed: data.seed,
        questions: data.questions,
        votes: votes,
      },
      null,
      1
    );
  }

  function download() {
    const blob = new Blob([votesJson()], { type: "application/json" });
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = "votes.json";
    document.body.append(a);
    a.click();
    a.remove();
  }

  document.addEventListener("keydown", (ev) => {
    if (ev.key >= "1" && ev.key <= "9") {
      vote(parseInt(ev.key, 10) - 1);
    }
  });
  $("download").addEventListener("click", download);
  window.QCStudy = { votes, votesJson, finished };
  show();
})();
